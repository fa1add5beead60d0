# syntax=docker/dockerfile:1
# The renderfarm worker (C++, Embree). Build from the repository root:
#   docker build -f deploy/docker/worker.Dockerfile -t renderfarm/worker:0.1.0 .
# Configured by RENDERFARM_SERVER, RENDERFARM_WORKER_THREADS, RENDERFARM_WORKER_TOKEN,
# RENDERFARM_WORKER_ID and the TLS settings RENDERFARM_WORKER_TLS, RENDERFARM_WORKER_CA_FILE,
# RENDERFARM_WORKER_CERT_FILE, RENDERFARM_WORKER_KEY_FILE, RENDERFARM_WORKER_TLS_SERVER_NAME
# (worker-entrypoint.sh maps them to flags).

# ---- build: the apt packages the project builds with (scripts/install-deps.sh), then the
# worker exactly as `make worker` builds it.
FROM debian:bookworm-slim AS build
WORKDIR /src
COPY scripts/install-deps.sh scripts/install-deps.sh
RUN scripts/install-deps.sh --apt-only
COPY proto proto
COPY worker worker
RUN cmake -S worker -B build/worker -G Ninja -DCMAKE_BUILD_TYPE=Release \
 && cmake --build build/worker -j "$(nproc)" --target renderfarm-worker \
 && strip build/worker/renderfarm-worker \
 && build/worker/renderfarm-worker --version

# ---- runtime: the shared libraries the worker links against, nothing to build with.
FROM debian:bookworm-slim
ARG VERSION=0.1.0
LABEL org.opencontainers.image.title="renderfarm-worker" \
      org.opencontainers.image.description="Render farm worker: Embree path tracer that renders tasks leased by a renderfarm server" \
      org.opencontainers.image.version="${VERSION}" \
      org.opencontainers.image.licenses="Apache-2.0" \
      org.opencontainers.image.base.name="debian:bookworm-slim"
COPY scripts/install-deps.sh /usr/local/share/renderfarm/scripts/install-deps.sh
RUN /usr/local/share/renderfarm/scripts/install-deps.sh --runtime worker \
 && rm -rf /var/lib/apt/lists/* /var/cache/apt/archives/*.deb \
 && useradd --system --uid 10001 --user-group --home-dir /var/lib/renderfarm --create-home \
      --shell /usr/sbin/nologin renderfarm
COPY --from=build /src/build/worker/renderfarm-worker /usr/local/bin/renderfarm-worker
COPY deploy/docker/worker-entrypoint.sh /usr/local/bin/worker-entrypoint
COPY deploy/docker/worker-healthcheck.sh /usr/local/bin/worker-healthcheck
ENV RENDERFARM_WORKER_CACHE_DIR=/var/lib/renderfarm/scenes
USER 10001:10001
WORKDIR /var/lib/renderfarm
# Healthy while the gRPC port of a server of RENDERFARM_SERVER (one, or every server of the
# farm, comma-separated) accepts connections from here (the worker reconnects with backoff on
# its own; this makes a worker that reaches no server visible in `docker compose ps`).
HEALTHCHECK --interval=15s --timeout=3s --start-period=10s --retries=3 \
  CMD ["worker-healthcheck"]
STOPSIGNAL SIGTERM
ENTRYPOINT ["worker-entrypoint"]
