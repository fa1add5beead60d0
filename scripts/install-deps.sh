#!/usr/bin/env bash
# Installs what the project needs on Debian 12 and is missing: apt packages, then the Python
# virtual environment (.venv) with the server package and its development tools.
# Used by `make demo`, `make test` and CI (without options), and by the Dockerfiles in deploy/
# (with the options below); safe to run again (does nothing when all is there).
#
#   scripts/install-deps.sh                  build packages (apt) + .venv (editable, dev tools)
#   scripts/install-deps.sh --apt-only       only the apt packages the project builds with
#   scripts/install-deps.sh --web            only what the dashboard's build (web/) needs:
#                                            Node.js and npm (the server image's web stage)
#   scripts/install-deps.sh --runtime server|worker
#                                            only the apt packages that component needs to run
#                                            (the final stage of its container image)
#   scripts/install-deps.sh --server-venv DIR
#                                            the server package (not editable, no dev tools) in
#                                            a new virtual environment DIR (the server image);
#                                            needs the gRPC stubs (`make proto`) first
#   scripts/install-deps.sh --deploy-tools   what `make test-deploy` needs: docker-compose,
#                                            iproute2 and openssl (apt), kustomize,
#                                            kubernetes-validate (.venv)
#   scripts/install-deps.sh --blender        Blender as a Python module (bpy, PyPI) in its own
#                                            virtual environment .venv-blender, for the add-on's
#                                            tests (tests/test_blender_addon.py; `make test`)
#   scripts/install-deps.sh --mitsuba        Mitsuba 3 (PyPI) in its own virtual environment
#                                            .venv-mitsuba, for bench/worker_throughput.py
#                                            --mitsuba (a benchmark, not a test)
#   scripts/install-deps.sh --print GROUP    print a package group (build, web, runtime-server,
#                                            runtime-worker, deploy, deploy-pip, blender-pip,
#                                            mitsuba-pip) and exit
set -euo pipefail
cd "$(dirname "$0")/.."

# Everything `make build` compiles and links against, and Python for the server.
APT_BUILD=(
  build-essential cmake ninja-build pkg-config
  libembree-dev libopenimageio-dev openimageio-tools
  libgrpc++-dev libprotobuf-dev protobuf-compiler protobuf-compiler-grpc
  libtinygltf-dev nlohmann-json3-dev libssl-dev libgtest-dev libbenchmark-dev libpq-dev
  libdraco-dev libmeshoptimizer-dev  # the decoders of compressed meshes (Draco, meshopt)
  gltfpack  # writes EXT_meshopt_compression scenes for the loader's tests
  python3 python3-venv python3-pip python3-dev  # headers: the server's C merge loops
  chromium  # headless browser of the dashboard tests (tests/browser, driven by Playwright)
  prometheus  # scrapes a farm in tests/test_prometheus.py; promtool checks the exposition
  ffmpeg  # encodes the preview movies of animation jobs (H.264 by libx264)
  # The system libraries Blender's bpy module links (X11, input, session, OpenGL; it bundles
  # the rest), for the Blender add-on's tests.
  libx11-6 libxext6 libxrender1 libxfixes3 libxi6 libxkbcommon0 libxcb1 libsm6 libice6 libgl1
)
# The dashboard's build (web/: npm ci, npm run build); any recent Node already on the machine is
# used, Debian's otherwise.
APT_WEB=(nodejs npm)
# The shared libraries build/worker/renderfarm-worker is linked against (objdump -p: NEEDED),
# by the Debian package that ships each; apt brings their own dependencies.
APT_RUNTIME_WORKER=(
  libgrpc++1.51 libgrpc29 libabsl20220623 libprotobuf32 libembree3-3 libopenimageio2.4
  libtinygltf2d libssl3 libstdc++6 libdraco7 libmeshoptimizer2d
  ca-certificates  # the system's CAs, which `connect --tls` checks the server against
)
# The server runs from a virtual environment whose wheels bundle their native libraries
# (grpcio, OpenImageIO, psycopg-binary, the embedded PostgreSQL); it needs the interpreter,
# openssl for the farm's certificates (deploy/docker/make-certs.sh), util-linux's prlimit,
# ffmpeg for preview movies, and the worker's libraries: it checks every uploaded scene with
# the worker's own loader (`renderfarm-worker inspect`, server/renderfarm/infra/scene_check.py).
APT_RUNTIME_SERVER=(
  python3 libssl3 libstdc++6 openssl util-linux "${APT_RUNTIME_WORKER[@]}"
  ffmpeg  # preview movies of animation jobs (server/renderfarm/infra/movie.py)
)
# The deployment checks: `docker-compose config` validates deploy/compose.yaml, iproute2 builds
# the network namespaces of the multi-host test, openssl makes its certificates.
APT_DEPLOY=(docker-compose iproute2 openssl)
# Offline validation of the Kubernetes manifests against the API types (schemas in the wheel).
PIP_DEPLOY=(kubernetes-validate==1.37.0)
KUSTOMIZE_MODULE=sigs.k8s.io/kustomize/kustomize/v5@v5.5.0
# Blender 5.0's Python as a module, for the add-on's tests (integrations/blender). It lives in
# .venv-blender, apart from .venv: bpy 5.0.1 requires numpy < 2 and OpenImageIO 3.2 (the
# server's) numpy >= 2. The wheel is ~375 MB (about 1 GB installed). Python 3.11, as Blender 5.0.
PIP_BLENDER=(bpy==5.0.1)
# Mitsuba 3, the peer bench/worker_throughput.py --mitsuba times on the Cornell box. 3.5.2: the
# Dr.Jit of later releases (3.9.1 tried) emits LLVM's fminimum, which Debian 12's LLVM 14 and 15
# (its JIT backend for the llvm_* variants) cannot select on x86.
PIP_MITSUBA=(mitsuba==3.5.2 numpy)

SUDO=""
[ "$(id -u)" -eq 0 ] || SUDO="sudo"

apt_install() {
  local missing=() pkg
  for pkg in "$@"; do
    dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "install ok installed" || missing+=("$pkg")
  done
  if [ ${#missing[@]} -gt 0 ]; then
    echo "installing Debian packages: ${missing[*]}"
    $SUDO apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}"
  fi
}

python_venv() {
  PYTHON=${PYTHON:-python3}
  if [ ! -x .venv/bin/python ]; then
    echo "creating the Python virtual environment in .venv"
    "$PYTHON" -m venv .venv
  fi
  local stamp
  # Installed again when the package's metadata or its compiled part changes.
  stamp=.venv/.installed-$(cat server/pyproject.toml server/setup.py server/renderfarm/_kernels.c |
    sha256sum | cut -c1-16)
  if [ ! -f "$stamp" ]; then
    echo "installing the server package and its dependencies into .venv"
    .venv/bin/pip install -q --upgrade pip
    .venv/bin/pip install -q -e 'server[dev]'
    rm -f .venv/.installed-*
    touch "$stamp"
  fi
}

server_venv() {
  local dir=$1
  if ! ls server/renderfarm/v1/*_pb2.py >/dev/null 2>&1; then
    echo "install-deps.sh --server-venv: no gRPC stubs in server/renderfarm/v1; run make proto" >&2
    exit 1
  fi
  "${PYTHON:-python3}" -m venv "$dir"
  "$dir/bin/pip" install -q --no-cache-dir --upgrade pip
  "$dir/bin/pip" install -q --no-cache-dir ./server
}

have_kustomize() {
  command -v kustomize >/dev/null 2>&1 && return 0
  [ -x .venv/bin/kustomize ] && return 0
  # kubectl has kustomize built in; v1.21 and later embed kustomize v4+, which is enough.
  command -v kubectl >/dev/null 2>&1 && kubectl kustomize --help >/dev/null 2>&1 &&
    kubectl version --client 2>/dev/null | grep -Eq 'Kustomize Version: v[4-9]'
}

deploy_tools() {
  apt_install "${APT_DEPLOY[@]}"
  python_venv
  local stamp
  stamp=.venv/.deploy-$(printf '%s\n' "${PIP_DEPLOY[@]}" | sha256sum | cut -c1-16)
  if [ ! -f "$stamp" ]; then
    echo "installing ${PIP_DEPLOY[*]} into .venv"
    .venv/bin/pip install -q "${PIP_DEPLOY[@]}"
    rm -f .venv/.deploy-*
    touch "$stamp"
  fi
  if ! have_kustomize; then
    # Debian 12 has no kustomize of its own: build it from its Go module.
    command -v go >/dev/null 2>&1 || apt_install golang-go
    echo "building kustomize ($KUSTOMIZE_MODULE) into .venv/bin"
    GOBIN="$PWD/.venv/bin" GOFLAGS=-mod=mod go install "$KUSTOMIZE_MODULE"
  fi
}

# A virtual environment DIR of its own with the pip packages given, installed once: a stamp
# named by their hash says it is done (a new list installs again).
pip_venv() {
  local dir=$1 stamp
  shift
  stamp=$dir/.installed-$(printf '%s\n' "$@" | sha256sum | cut -c1-16)
  if [ ! -f "$stamp" ]; then
    echo "installing $* into $dir"
    [ -x "$dir/bin/python" ] || "${PYTHON:-python3}" -m venv "$dir"
    "$dir/bin/pip" install -q "$@"
    rm -f "$dir"/.installed-*
    touch "$stamp"
  fi
}

blender_venv() {
  apt_install "${APT_BUILD[@]}"
  pip_venv .venv-blender "${PIP_BLENDER[@]}"
}

mitsuba_venv() {
  apt_install python3 python3-venv libllvm15  # libLLVM-15.so: the llvm_* variants' JIT
  pip_venv .venv-mitsuba "${PIP_MITSUBA[@]}"
}

case "${1:-}" in
  "")
    apt_install "${APT_BUILD[@]}"
    command -v npm >/dev/null 2>&1 || apt_install "${APT_WEB[@]}"
    python_venv
    ;;
  --apt-only)
    apt_install "${APT_BUILD[@]}"
    ;;
  --web)
    command -v npm >/dev/null 2>&1 || apt_install "${APT_WEB[@]}"
    ;;
  --runtime)
    case "${2:-}" in
      server) apt_install "${APT_RUNTIME_SERVER[@]}" ;;
      worker) apt_install "${APT_RUNTIME_WORKER[@]}" ;;
      *) echo "usage: $0 --runtime server|worker" >&2; exit 2 ;;
    esac
    ;;
  --server-venv)
    [ -n "${2:-}" ] || { echo "usage: $0 --server-venv DIR" >&2; exit 2; }
    server_venv "$2"
    ;;
  --deploy-tools)
    deploy_tools
    ;;
  --blender)
    blender_venv
    ;;
  --mitsuba)
    mitsuba_venv
    ;;
  --print)
    case "${2:-}" in
      build) printf '%s\n' "${APT_BUILD[@]}" ;;
      web) printf '%s\n' "${APT_WEB[@]}" ;;
      runtime-server) printf '%s\n' "${APT_RUNTIME_SERVER[@]}" ;;
      runtime-worker) printf '%s\n' "${APT_RUNTIME_WORKER[@]}" ;;
      deploy) printf '%s\n' "${APT_DEPLOY[@]}" ;;
      deploy-pip) printf '%s\n' "${PIP_DEPLOY[@]}" ;;
      blender-pip) printf '%s\n' "${PIP_BLENDER[@]}" ;;
      mitsuba-pip) printf '%s\n' "${PIP_MITSUBA[@]}" ;;
      *) echo "usage: $0 --print build|web|runtime-server|runtime-worker|deploy|deploy-pip|blender-pip|mitsuba-pip" >&2; exit 2 ;;
    esac
    ;;
  *)
    sed -n '2,26p' "$0" >&2
    exit 2
    ;;
esac
