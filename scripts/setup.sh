#!/usr/bin/env bash
# Installs what a fresh Debian 12 machine lacks to build, test and run Texel:
# system packages (quietly, only the missing ones) and the Python venv of peer tools
# (cached outside the repository, rebuilt only when requirements change).
# Idempotent: a second run does nothing but check.
set -euo pipefail

repo="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"

# Packages: lavapipe (software Vulkan) for wgpu; Xvfb and X client libraries for the
# windowed viewer; libclang for the v4l crate's bindgen; libusb for Open3D; LLVM 19
# for Mitsuba's LLVM backend; DejaVu fonts for the text of plots; g++ for meshoptimizer;
# clang for the C and C++ the browser viewer compiles to wasm32; Chromium for CesiumJS,
# the independent 3D Tiles viewer the exports are checked in, and for the browser
# viewer's test.
packages=(
  mesa-vulkan-drivers libvulkan1 xvfb xauth libxcursor1 libxi6 libxrandr2
  libxkbcommon-x11-0 libx11-xcb1 libclang-dev libusb-1.0-0 libllvm19 pkg-config fonts-dejavu-core
  g++ clang chromium
)

missing=()
for p in "${packages[@]}"; do
  if ! dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed"; then
    missing+=("$p")
  fi
done
if [ ${#missing[@]} -gt 0 ]; then
  sudo=""
  if [ "$(id -u)" -ne 0 ]; then sudo="sudo"; fi
  echo "setup: installing ${missing[*]}" >&2
  $sudo env DEBIAN_FRONTEND=noninteractive apt-get update -qq
  $sudo env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends \
    "${missing[@]}" >/dev/null
fi

# The Python venv, outside the clone.
venv="${TEXEL_VENV:-${XDG_CACHE_HOME:-$HOME/.cache}/texel/venv}"
req="$repo/scripts/python/requirements.txt"
stamp="$venv/.texel-requirements"
if [ ! -x "$venv/bin/python" ] || ! cmp -s "$req" "$stamp"; then
  echo "setup: creating the Python venv at $venv" >&2
  mkdir -p "$(dirname "$venv")"
  python3 -m venv "$venv"
  "$venv/bin/python" -m pip install -q --no-cache-dir --disable-pip-version-check --upgrade pip
  "$venv/bin/python" -m pip install -q --no-cache-dir --disable-pip-version-check -r "$req"
  cp "$req" "$stamp"
fi

# The Node.js peer checks (Khronos glTF validator, a JSON Schema validator for the 3D
# Tiles schema, loaders.gl's 3D Tiles reader, CesiumJS driven in Chromium by
# playwright-core), outside the clone, reinstalled only when
# the lock file changes. Node.js and npm come from Debian when the machine has none.
if ! command -v node >/dev/null 2>&1 || ! command -v npm >/dev/null 2>&1; then
  sudo=""
  if [ "$(id -u)" -ne 0 ]; then sudo="sudo"; fi
  echo "setup: installing nodejs npm" >&2
  $sudo env DEBIAN_FRONTEND=noninteractive apt-get update -qq
  $sudo env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends \
    nodejs npm >/dev/null
fi
node_dir="${TEXEL_NODE_DIR:-${XDG_CACHE_HOME:-$HOME/.cache}/texel/node}"
node_lock="$repo/scripts/node/package-lock.json"
if [ ! -d "$node_dir/node_modules" ] || ! cmp -s "$node_lock" "$node_dir/package-lock.json"; then
  echo "setup: installing the Node.js peer checks at $node_dir" >&2
  mkdir -p "$node_dir"
  cp "$repo/scripts/node/package.json" "$node_lock" "$node_dir/"
  (cd "$node_dir" && npm ci --no-audit --no-fund --loglevel=error >/dev/null)
fi
