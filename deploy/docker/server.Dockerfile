# syntax=docker/dockerfile:1
# The renderfarm server (REST :8080, gRPC :50051). Build from the repository root:
#   docker build -f deploy/docker/server.Dockerfile -t renderfarm/server:0.1.0 .
# Configured only by RENDERFARM_* environment variables (docs/settings.md, "Server settings").

# ---- web: the dashboard, built with the commands of the Makefile's `web` target (npm ci from
# web/package-lock.json, then npm run build: type check and bundle into web/dist).
FROM debian:bookworm-slim AS web
WORKDIR /src
COPY scripts/install-deps.sh scripts/install-deps.sh
RUN scripts/install-deps.sh --web
COPY web web
RUN cd web \
 && npm ci --no-audit --no-fund --loglevel=error \
 && npm run --silent build

# ---- worker: the renderfarm-worker binary, built as worker.Dockerfile builds it. The server
# runs its loader on every uploaded scene (`renderfarm-worker inspect`), so that it accepts
# only what the workers can load.
FROM debian:bookworm-slim AS worker
WORKDIR /src
COPY scripts/install-deps.sh scripts/install-deps.sh
RUN scripts/install-deps.sh --apt-only
COPY proto proto
COPY worker worker
RUN cmake -S worker -B build/worker -G Ninja -DCMAKE_BUILD_TYPE=Release \
 && cmake --build build/worker -j "$(nproc)" --target renderfarm-worker \
 && strip build/worker/renderfarm-worker \
 && build/worker/renderfarm-worker --version

# ---- build: the same set-up as `make demo`, `make test` and CI (scripts/install-deps.sh,
# `make proto`), then the server package alone into /opt/renderfarm. The dashboard goes into the
# package as its data (renderfarm/web), where the installed server looks for it.
FROM debian:bookworm-slim AS build
WORKDIR /src
COPY scripts/install-deps.sh scripts/install-deps.sh
RUN scripts/install-deps.sh --apt-only
COPY Makefile ./
COPY proto proto
COPY server server
COPY --from=web /src/web/dist server/renderfarm/web
RUN scripts/install-deps.sh \
 && make proto \
 && scripts/install-deps.sh --server-venv /opt/renderfarm \
 && find /opt/renderfarm -name '__pycache__' -prune -exec rm -rf {} + \
 && rm -rf /opt/renderfarm/lib/python3*/site-packages/pip

# ---- runtime: Python, the virtual environment and the worker binary (with the shared
# libraries of both), nothing to build with.
FROM debian:bookworm-slim
ARG VERSION=0.1.0
LABEL org.opencontainers.image.title="renderfarm-server" \
      org.opencontainers.image.description="Render farm server: REST API, dashboard, gRPC job and worker services, scheduler" \
      org.opencontainers.image.version="${VERSION}" \
      org.opencontainers.image.licenses="Apache-2.0" \
      org.opencontainers.image.base.name="debian:bookworm-slim"
COPY scripts/install-deps.sh /usr/local/share/renderfarm/scripts/install-deps.sh
RUN /usr/local/share/renderfarm/scripts/install-deps.sh --runtime server \
 && rm -rf /var/lib/apt/lists/* /var/cache/apt/archives/*.deb \
 && useradd --system --uid 10001 --user-group --home-dir /var/lib/renderfarm --create-home \
      --shell /usr/sbin/nologin renderfarm
COPY --from=build /opt/renderfarm /opt/renderfarm
COPY --from=worker /src/build/worker/renderfarm-worker /usr/local/bin/renderfarm-worker
# Makes a private CA and the farm's certificates when there are none (compose's `certs` service).
COPY deploy/docker/make-certs.sh /usr/local/bin/renderfarm-make-certs
ENV PATH=/opt/renderfarm/bin:$PATH \
    PYTHONUNBUFFERED=1 \
    PYTHONDONTWRITEBYTECODE=1 \
    RENDERFARM_DATA_DIR=/var/lib/renderfarm \
    RENDERFARM_HTTP_HOST=0.0.0.0 \
    RENDERFARM_GRPC_HOST=0.0.0.0
USER 10001:10001
WORKDIR /var/lib/renderfarm
EXPOSE 8080 50051
# https when the server has a certificate. Readiness of the process on loopback: the certificate
# is the clients' concern (its names need not include 127.0.0.1), so it is not checked here.
HEALTHCHECK --interval=10s --timeout=3s --start-period=30s --retries=3 \
  CMD ["python3", "-c", "import os, ssl, urllib.request; tls = bool(os.environ.get('RENDERFARM_TLS_CERT_FILE')); urllib.request.urlopen('%s://127.0.0.1:%s/readyz' % ('https' if tls else 'http', os.environ.get('RENDERFARM_HTTP_PORT', '8080')), timeout=2, context=ssl._create_unverified_context() if tls else None)"]
ENTRYPOINT ["renderfarm", "server"]
