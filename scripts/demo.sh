#!/usr/bin/env bash
# `make demo`: start a local farm (embedded PostgreSQL, server, 2 workers) in the background,
# render the Cornell box on it, print where the image and the dashboard are. The farm keeps
# running so the dashboard can be looked at; `make stop` stops it.
set -euo pipefail
cd "$(dirname "$0")/.."
STATE=.farm
PIDFILE=$STATE/farm.pid
HTTP_PORT=${RENDERFARM_HTTP_PORT:-8080}
GRPC_PORT=${RENDERFARM_GRPC_PORT:-50051}
URL=http://127.0.0.1:$HTTP_PORT
mkdir -p $STATE out

running() { [ -f $PIDFILE ] && kill -0 "$(cat $PIDFILE)" 2>/dev/null; }

if [ "${1:-}" = stop ]; then
  if running; then
    kill -TERM "$(cat $PIDFILE)"
    for _ in $(seq 1 100); do running || break; sleep 0.2; done
    echo "local farm stopped"
  else
    echo "no local farm running"
  fi
  rm -f $PIDFILE
  exit 0
fi

if ! running; then
  echo "starting the local farm (embedded PostgreSQL, server, 2 workers); log: $STATE/farm.log"
  nohup .venv/bin/renderfarm up --workers 2 --data-dir "$PWD/$STATE/data" \
    --http-port "$HTTP_PORT" --grpc-port "$GRPC_PORT" > $STATE/farm.log 2>&1 &
  echo $! > $PIDFILE
fi
for i in $(seq 1 600); do
  curl -sf "$URL/readyz" >/dev/null 2>&1 && break
  if ! running; then echo "the farm did not start; see $STATE/farm.log" >&2; tail -20 $STATE/farm.log >&2; exit 1; fi
  [ "$i" = 600 ] && { echo "the farm was not ready after 120 s; see $STATE/farm.log" >&2; exit 1; }
  sleep 0.2
done
# Wait (bounded) for both workers to connect so the render uses them from the start.
for _ in $(seq 1 100); do
  [ "$(curl -sf "$URL/api/v1/workers" | .venv/bin/python -c 'import json,sys; print(len(json.load(sys.stdin)))')" -ge 2 ] && break
  sleep 0.2
done

.venv/bin/renderfarm render examples/cornell-box.gltf -o out/cornell-box.exr --url "$URL" \
  --width 512 --height 512 --noise-threshold 0.08 --max-spp 1024
echo "Dashboard: $URL/   API docs: $URL/docs"
echo "The farm keeps running; stop it with: make stop"
