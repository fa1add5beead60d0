#!/bin/sh
# Makes the TLS certificates of a farm when there are none: a private CA, the server's
# certificate (signed by it, for the names given) and one client certificate for the workers
# (mutual TLS). Used by deploy/compose.yaml (its one-shot `certs` service, in the server image as
# renderfarm-make-certs) and by deploy/netns/farm.sh. Needs openssl.
#
#   make-certs.sh [--owner UID:GID] SERVER_DIR WORKER_DIR NAME[,NAME...] [NAME...]
#
# SERVER_DIR gets tls.crt and tls.key (the server's certificate and key) and ca.crt (the CA, for
# RENDERFARM_TLS_CLIENT_CA_FILE); WORKER_DIR gets ca.crt (to check the server with) and tls.crt and
# tls.key (the workers' client certificate). The same names as in the Secrets cert-manager makes
# for deploy/k8s. NAMEs are the server's DNS names and IP addresses (the first is also its common
# name); empty ones are skipped. --owner: chown the files (a root container writing for the
# server's user). The CA's key is not kept: nothing else is ever signed with it; remove both
# directories' files to make new ones.
#
# When SERVER_DIR/tls.crt exists (made before, or an operator's own certificate) nothing is made;
# it only checks that the files the farm reads are there, and exits 1 naming one that is not.
set -eu

die() { echo "make-certs: $*" >&2; exit 1; }

owner=""
if [ "${1:-}" = "--owner" ]; then
  [ -n "${2:-}" ] || die "--owner needs UID:GID"
  owner=$2
  shift 2
fi
[ $# -ge 3 ] || die "usage: make-certs.sh [--owner UID:GID] SERVER_DIR WORKER_DIR NAME[,NAME...] [NAME...]"
server_dir=$1
worker_dir=$2
shift 2

if [ -f "$server_dir/tls.crt" ]; then
  for f in "$server_dir/tls.key" "$worker_dir/ca.crt"; do
    [ -f "$f" ] || die "$server_dir/tls.crt exists but $f does not: add it (see docs/operations.md, TLS of the deployments)"
  done
  echo "make-certs: certificates present in $server_dir and $worker_dir; nothing to do"
  exit 0
fi
command -v openssl >/dev/null 2>&1 || die "openssl is missing"

# The server's subjectAltName: IP:... for addresses, DNS:... for names.
sans=""
cn=""
for arg in "$@"; do
  for name in $(echo "$arg" | tr ',' ' '); do
    case "$name" in
      *:*) kind=IP ;;         # IPv6
      *[!0-9.]*) kind=DNS ;;
      *) kind=IP ;;           # IPv4
    esac
    sans="${sans:+$sans,}$kind:$name"
    [ -n "$cn" ] || cn=$name
  done
done
[ -n "$sans" ] || die "no server name given"

mkdir -p "$server_dir" "$worker_dir"
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
umask 077
serial() { echo "0x$(od -An -N16 -tx1 /dev/urandom | tr -d ' \n')"; }

# ECDSA P-256 keys; the CA for ten years, the leaf certificates for 825 days (the longest
# validity some TLS clients accept for a server certificate).
openssl req -x509 -new -newkey ec -pkeyopt ec_paramgen_curve:P-256 -nodes -sha256 \
  -keyout "$work/ca.key" -out "$work/ca.crt" -days 3650 -subj "/CN=renderfarm CA" \
  -set_serial "$(serial)" \
  -addext "basicConstraints=critical,CA:TRUE" -addext "keyUsage=critical,keyCertSign,cRLSign" \
  2>"$work/log" || { cat "$work/log" >&2; die "openssl could not make the CA"; }

leaf() {  # leaf NAME SUBJECT EXTENSIONS: NAME.key and NAME.crt signed by the CA
  printf '%s\n' "$3" > "$work/$1.ext"
  openssl req -new -newkey ec -pkeyopt ec_paramgen_curve:P-256 -nodes -sha256 \
    -keyout "$work/$1.key" -out "$work/$1.csr" -subj "$2" 2>"$work/log" &&
    openssl x509 -req -in "$work/$1.csr" -CA "$work/ca.crt" -CAkey "$work/ca.key" -sha256 \
      -days 825 -set_serial "$(serial)" -extfile "$work/$1.ext" -out "$work/$1.crt" \
      2>>"$work/log" || { cat "$work/log" >&2; die "openssl could not make the $1 certificate"; }
}
leaf server "/CN=$cn" "basicConstraints=critical,CA:FALSE
keyUsage=critical,digitalSignature
extendedKeyUsage=serverAuth
subjectAltName=$sans"
leaf worker "/CN=renderfarm-worker" "basicConstraints=critical,CA:FALSE
keyUsage=critical,digitalSignature
extendedKeyUsage=clientAuth"

install_file() {  # install_file SOURCE DEST MODE
  cp "$1" "$2.new"
  chmod "$3" "$2.new"
  [ -z "$owner" ] || chown "$owner" "$2.new"
  mv -f "$2.new" "$2"
}
install_file "$work/ca.crt" "$worker_dir/ca.crt" 644
install_file "$work/worker.crt" "$worker_dir/tls.crt" 644
install_file "$work/worker.key" "$worker_dir/tls.key" 600
install_file "$work/ca.crt" "$server_dir/ca.crt" 644
install_file "$work/server.key" "$server_dir/tls.key" 600
# Last: its presence means the set is complete.
install_file "$work/server.crt" "$server_dir/tls.crt" 644
echo "make-certs: made a CA and certificates for $sans in $server_dir and $worker_dir"
