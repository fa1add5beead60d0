#!/bin/sh
# Entrypoint of the worker image (and of the worker hosts of deploy/netns/farm.sh): maps the
# environment to `renderfarm-worker connect` flags and execs the worker, so that it is the
# container's main process and SIGTERM (docker stop, Kubernetes' preStop drain) reaches it: it
# finishes the tasks in hand and exits 0.
#
#   RENDERFARM_SERVER            host:port of the server's gRPC API (required)
#   RENDERFARM_WORKER_THREADS    render threads (default: every core)           --threads
#   RENDERFARM_WORKER_PREFETCH   tasks leased beyond the threads (default 1)    --prefetch
#   RENDERFARM_WORKER_TOKEN      the server's RENDERFARM_WORKER_TOKEN, if set   --token
#   RENDERFARM_WORKER_ID         worker id (default: the host name)             --id
#   RENDERFARM_WORKER_CACHE_DIR  scene cache directory                          --cache-dir
#   RENDERFARM_WORKER_BINARY     the worker binary (default: renderfarm-worker on PATH)
#
# Arguments are appended to the connect flags; a first argument that is not a flag runs the
# binary with exactly those arguments instead (`docker run IMAGE render scene.glb -o x.exr ...`).
set -eu

bin=${RENDERFARM_WORKER_BINARY:-renderfarm-worker}

case "${1:-}" in
  "" | -*) ;;
  *) exec "$bin" "$@" ;;
esac

if [ -z "${RENDERFARM_SERVER:-}" ]; then
  echo "worker-entrypoint: RENDERFARM_SERVER (host:port of the server's gRPC API) is not set" >&2
  exit 64
fi

# Build the argument list back to front so that the caller's own arguments come last.
set -- connect --server "$RENDERFARM_SERVER" \
  ${RENDERFARM_WORKER_THREADS:+--threads "$RENDERFARM_WORKER_THREADS"} \
  ${RENDERFARM_WORKER_PREFETCH:+--prefetch "$RENDERFARM_WORKER_PREFETCH"} \
  ${RENDERFARM_WORKER_TOKEN:+--token "$RENDERFARM_WORKER_TOKEN"} \
  ${RENDERFARM_WORKER_ID:+--id "$RENDERFARM_WORKER_ID"} \
  ${RENDERFARM_WORKER_CACHE_DIR:+--cache-dir "$RENDERFARM_WORKER_CACHE_DIR"} \
  "$@"
exec "$bin" "$@"
