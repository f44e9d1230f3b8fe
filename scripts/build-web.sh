#!/usr/bin/env bash
# Builds the field display (the browser viewer) into target/web: texel-viewer's library
# for wasm32 as a cdylib, bound to JavaScript by wasm-bindgen (the version pinned in
# Cargo.lock), beside viewer/web/index.html. texeld serves that folder on its viewer
# port. Installs clang, the wasm32 target and wasm-bindgen-cli when missing.
#   bash scripts/build-web.sh
set -euo pipefail
repo="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$repo"
out="$repo/target/web"
wasm="$repo/target/wasm32-unknown-unknown/release/texel_viewer.wasm"

# clang compiles the C and C++ the viewer links (meshoptimizer, zstd, lz4) for wasm32.
if ! command -v clang >/dev/null 2>&1; then
  sudo=""
  if [ "$(id -u)" -ne 0 ]; then sudo="sudo"; fi
  echo "build-web: installing clang" >&2
  $sudo env DEBIAN_FRONTEND=noninteractive apt-get update -qq
  $sudo env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends clang >/dev/null
fi
if ! rustup target list --installed | grep -qx wasm32-unknown-unknown; then
  echo "build-web: adding the wasm32-unknown-unknown target" >&2
  rustup target add wasm32-unknown-unknown >/dev/null
fi
version="$(awk '/^name = "wasm-bindgen"$/ { getline; gsub(/[^0-9.]/, ""); print; exit }' Cargo.lock)"
if ! command -v wasm-bindgen >/dev/null 2>&1 || [ "$(wasm-bindgen --version | awk '{print $2}')" != "$version" ]; then
  echo "build-web: installing wasm-bindgen-cli $version" >&2
  cargo install -q wasm-bindgen-cli --version "$version"
fi

echo "build-web: building the viewer for wasm32" >&2
cargo rustc -q --locked --release -p texel-viewer --lib --target wasm32-unknown-unknown --crate-type cdylib
mkdir -p "$out"
wasm-bindgen --target web --no-typescript --out-dir "$out" --out-name texel_viewer_web "$wasm"
cp viewer/web/index.html "$out/index.html"
echo "build-web: the page is in $out ($(du -h "$out/texel_viewer_web_bg.wasm" | cut -f1) of wasm)" >&2
