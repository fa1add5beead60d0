#!/usr/bin/env bash
# Installs what the project needs on Debian 12 and is missing: apt packages, then the Python
# virtual environment (.venv) with the server package and its development tools.
# Used by `make demo`, `make test` and CI; safe to run again (does nothing when all is there).
set -euo pipefail
cd "$(dirname "$0")/.."

APT_PACKAGES=(
  build-essential cmake ninja-build pkg-config
  libembree-dev libopenimageio-dev openimageio-tools
  libgrpc++-dev libprotobuf-dev protobuf-compiler protobuf-compiler-grpc
  libtinygltf-dev nlohmann-json3-dev libssl-dev libgtest-dev libbenchmark-dev libpq-dev
  python3 python3-venv python3-pip
)

missing=()
for pkg in "${APT_PACKAGES[@]}"; do
  dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "install ok installed" || missing+=("$pkg")
done
if [ ${#missing[@]} -gt 0 ]; then
  echo "installing Debian packages: ${missing[*]}"
  SUDO=""
  [ "$(id -u)" -eq 0 ] || SUDO="sudo"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}"
fi

PYTHON=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  echo "creating the Python virtual environment in .venv"
  "$PYTHON" -m venv .venv
fi
stamp=.venv/.installed-$(sha256sum server/pyproject.toml | cut -c1-16)
if [ ! -f "$stamp" ]; then
  echo "installing the server package and its dependencies into .venv"
  .venv/bin/pip install -q --upgrade pip
  .venv/bin/pip install -q -e 'server[dev]'
  rm -f .venv/.installed-*
  touch "$stamp"
fi
