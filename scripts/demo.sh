#!/usr/bin/env bash
# `make demo [SCENE=...]`: start a local farm (embedded PostgreSQL, server, 2 workers) in the
# background, render a scene on it (the Cornell box unless SCENE names another), print where
# the image and the dashboard are. The farm keeps running so the dashboard can be looked at;
# `make stop` stops it.
#
#   scripts/demo.sh [SCENE]            render SCENE: an example's short name or a .glb/.gltf path
#   scripts/demo.sh --resolve [SCENE]  only print what SCENE resolves to (starts nothing)
#   scripts/demo.sh stop               stop the local farm
#
# A scene that is neither an example nor an existing .glb/.gltf file is one error line and
# exit status 2, before anything starts.
set -euo pipefail
ROOT=$(cd "$(dirname "$0")/.." && pwd)

# The examples: short name, file, generator (empty: the file is committed), width, height,
# noise threshold, max spp. Each is sized to finish in a few minutes on 2 local workers.
EXAMPLES="
cornell-box examples/cornell-box.gltf -                        512 512 0.08 1024
studio      examples/studio.glb       examples/make_studio.py  512 384 0.1  512
hinged-box  examples/hinged-box.glb   examples/make_hinged_box.py 480 360 0.08 256
"
NAMES=$(echo "$EXAMPLES" | awk 'NF {printf "%s%s", sep, $1; sep=", "}')

# resolve SCENE: sets SCENE_FILE (relative to ROOT for an example, absolute for a path),
# GENERATOR, NAME (the output's name), WIDTH, HEIGHT, NOISE, MAX_SPP; or exits 2.
resolve() {
  local scene=${1:-cornell-box}
  [ "$scene" = cornell ] && scene=cornell-box
  local row
  row=$(echo "$EXAMPLES" | awk -v n="$scene" '$1 == n')
  if [ -z "$row" ] && [ -f "$scene" ]; then  # an example's file by its path: its settings
    row=$(echo "$EXAMPLES" | awk -v f="$(realpath "$scene")" -v r="$ROOT" 'NF && r "/" $2 == f')
  fi
  if [ -n "$row" ]; then
    read -r NAME SCENE_FILE GENERATOR WIDTH HEIGHT NOISE MAX_SPP <<< "$row"
    if [ "$GENERATOR" = - ]; then GENERATOR=; fi
    return 0
  fi
  case "$scene" in
    *.glb | *.gltf) ;;
    */*) echo "demo: SCENE=$scene: not a .glb or .gltf file (examples: $NAMES)" >&2; exit 2 ;;
    *) echo "demo: SCENE=$scene: no such example (examples: $NAMES; or a path to a .glb/.gltf)" >&2; exit 2 ;;
  esac
  if [ ! -f "$scene" ]; then
    echo "demo: SCENE=$scene: no such file" >&2
    exit 2
  fi
  SCENE_FILE=$(realpath "$scene")
  GENERATOR=
  NAME=$(basename "${scene%.*}")
  WIDTH=640 HEIGHT=480 NOISE=0.1 MAX_SPP=512
}

if [ "${1:-}" = --resolve ]; then
  resolve "${2:-}"
  echo "scene=$SCENE_FILE generator=${GENERATOR:--} output=out/$NAME.exr width=$WIDTH height=$HEIGHT noise_threshold=$NOISE max_spp=$MAX_SPP"
  exit 0
fi
[ "${1:-}" = stop ] || resolve "${1:-}"  # before the cd: a relative path is the caller's

cd "$ROOT"
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

if [ -n "$GENERATOR" ] && [ ! -f "$SCENE_FILE" ]; then
  echo "writing $SCENE_FILE ($GENERATOR)"
  .venv/bin/python "$GENERATOR" -o "$SCENE_FILE" >/dev/null
fi
echo "rendering $SCENE_FILE at ${WIDTH}x$HEIGHT (noise threshold $NOISE, at most $MAX_SPP spp)"
.venv/bin/renderfarm render "$SCENE_FILE" -o "out/$NAME.exr" --url "$URL" \
  --width "$WIDTH" --height "$HEIGHT" --noise-threshold "$NOISE" --max-spp "$MAX_SPP"
echo "Dashboard: $URL/   API docs: $URL/docs"
echo "The farm keeps running; stop it with: make stop"
