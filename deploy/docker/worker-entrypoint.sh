#!/bin/sh
# Entrypoint of the worker image (and of the worker hosts of deploy/netns/farm.sh): maps the
# environment to `renderfarm-worker connect` flags and execs the worker, so that it is the
# container's main process and SIGTERM (docker stop, Kubernetes' preStop drain) reaches it: it
# finishes the tasks in hand and exits 0.
#
#   RENDERFARM_SERVER            host:port of the server's gRPC API (required)
#   RENDERFARM_WORKER_THREADS    render threads (default: every core)           --threads
#   RENDERFARM_WORKER_PREFETCH   tasks leased beyond the threads (default 1)    --prefetch
#   RENDERFARM_WORKER_RESULT_INTERVAL_MS  least time between result messages
#                                (default 50)                                   --result-interval-ms
#   RENDERFARM_WORKER_TOKEN      the server's RENDERFARM_WORKER_TOKEN, if set   --token
#   RENDERFARM_WORKER_ID         worker id (default: the host name)             --id
#   RENDERFARM_WORKER_CACHE_DIR  scene cache directory                          --cache-dir
#   RENDERFARM_WORKER_TLS        1: TLS, checked against the system's CAs       --tls
#   RENDERFARM_WORKER_CA_FILE    TLS, checked against this CA bundle instead    --ca-file
#   RENDERFARM_WORKER_CERT_FILE  client certificate (mutual TLS), with the key  --cert
#   RENDERFARM_WORKER_KEY_FILE   its private key                                --key
#   RENDERFARM_WORKER_TLS_SERVER_NAME  the name the server's certificate must have
#                                (default: the host of RENDERFARM_SERVER)        --tls-server-name
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
case "${RENDERFARM_WORKER_TLS:-}" in
  "" | 0) tls="" ;;
  1) tls=1 ;;
  *)
    echo "worker-entrypoint: RENDERFARM_WORKER_TLS must be 1 or 0, not '$RENDERFARM_WORKER_TLS'" >&2
    exit 64
    ;;
esac

# Build the argument list back to front so that the caller's own arguments come last.
set -- connect --server "$RENDERFARM_SERVER" \
  ${RENDERFARM_WORKER_THREADS:+--threads "$RENDERFARM_WORKER_THREADS"} \
  ${RENDERFARM_WORKER_PREFETCH:+--prefetch "$RENDERFARM_WORKER_PREFETCH"} \
  ${RENDERFARM_WORKER_RESULT_INTERVAL_MS:+--result-interval-ms "$RENDERFARM_WORKER_RESULT_INTERVAL_MS"} \
  ${RENDERFARM_WORKER_TOKEN:+--token "$RENDERFARM_WORKER_TOKEN"} \
  ${RENDERFARM_WORKER_ID:+--id "$RENDERFARM_WORKER_ID"} \
  ${RENDERFARM_WORKER_CACHE_DIR:+--cache-dir "$RENDERFARM_WORKER_CACHE_DIR"} \
  ${tls:+--tls} \
  ${RENDERFARM_WORKER_CA_FILE:+--ca-file "$RENDERFARM_WORKER_CA_FILE"} \
  ${RENDERFARM_WORKER_CERT_FILE:+--cert "$RENDERFARM_WORKER_CERT_FILE"} \
  ${RENDERFARM_WORKER_KEY_FILE:+--key "$RENDERFARM_WORKER_KEY_FILE"} \
  ${RENDERFARM_WORKER_TLS_SERVER_NAME:+--tls-server-name "$RENDERFARM_WORKER_TLS_SERVER_NAME"} \
  "$@"
exec "$bin" "$@"
