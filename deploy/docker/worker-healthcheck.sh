#!/bin/bash
# Health check of the worker image (its HEALTHCHECK, and deploy/compose.yaml's): healthy while
# the gRPC port of at least one server of RENDERFARM_SERVER (host:port, or several
# comma-separated: every server of a farm) accepts a TCP connection from here, each tried for
# at most a second. One server of several away (restarted, updated, stopped) leaves the worker
# rendering for the others: still healthy. The worker reconnects with backoff on its own; this
# only makes a worker that reaches no server visible (`docker compose ps`).
set -u

IFS=, read -ra entries <<< "${RENDERFARM_SERVER:-}"
for entry in "${entries[@]}"; do
  entry=${entry// /}
  host=${entry%:*} port=${entry##*:}
  [ -n "$host" ] && [ "$host" != "$entry" ] || continue
  host=${host#[} host=${host%]}  # [v6 address]:port
  if timeout 1 bash -c 'exec 3<>"/dev/tcp/$0/$1"' "$host" "$port" 2>/dev/null; then
    exit 0
  fi
done
echo "worker-healthcheck: no server of RENDERFARM_SERVER='${RENDERFARM_SERVER:-}' accepts" >&2
exit 1
