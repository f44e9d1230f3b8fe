#!/usr/bin/env bash
# The main job on one machine: the daemon on the simulated texel camera (the `lab`
# scene, registered as it goes; configs/sessions/demo-lab.toml, which waits for every
# frame rather than skipping late ones) with the viewer attached. With a display the viewer
# opens a window; without one it renders snapshots of the live model to a folder and
# says where. The daemon also serves the field display (the browser viewer) on the
# same port; the script prints its address. Ctrl-C stops both cleanly.
#   bash scripts/demo.sh
# Environment: TEXEL_DEMO_ADDR (default 127.0.0.1:7878), TEXEL_DEMO_SNAPSHOTS (the
# snapshot folder, default demo-snapshots), TEXEL_DEMO_CONFIG (the session file).
set -euo pipefail

repo="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$repo"

addr="${TEXEL_DEMO_ADDR:-127.0.0.1:7878}"
config="${TEXEL_DEMO_CONFIG:-configs/sessions/demo-lab.toml}"
snapshots="${TEXEL_DEMO_SNAPSHOTS:-demo-snapshots}"

bash scripts/setup.sh
echo "demo: building release binaries" >&2
cargo build --release --locked -q -p texel-daemon -p texel-viewer -p sims
# The field display: the browser viewer the daemon serves on its viewer port.
bash scripts/build-web.sh
bin="$repo/target/release"

daemon_pid=""
viewer_pid=""
stop() {
  trap - INT TERM
  echo "demo: stopping" >&2
  # The viewer first (it would only retry), then the daemon, which drains its
  # pipeline, finalises its recording and tells its viewers.
  for pid in "$viewer_pid" "$daemon_pid"; do
    if [ -n "$pid" ] && kill -0 "$pid" 2>/dev/null; then
      kill -TERM "$pid" 2>/dev/null || true
      wait "$pid" 2>/dev/null || true
    fi
  done
  exit 0
}
trap stop INT TERM

if [ -f "$config" ]; then
  # The session records into captures/ (git-ignored, so absent from a fresh clone);
  # the daemon does not create folders for its recording.
  mkdir -p captures
  echo "demo: starting texeld run --config $config on $addr" >&2
  "$bin/texeld" run --config "$config" --bind "$addr" &
  daemon_pid=$!
else
  # Without the simulated-source session file: a simulated capture of the same
  # scene, replayed through the daemon in real time.
  capture="target/demo/lab.mcap"
  if [ ! -f "$capture" ]; then
    mkdir -p target/demo
    echo "demo: $config not found; rendering the lab scene into $capture" >&2
    "$bin/texel-sims" render --scene configs/scenes/lab.toml --out "$capture"
  fi
  echo "demo: starting texeld replay $capture on $addr" >&2
  "$bin/texeld" replay "$capture" --speed 1 --stay --bind "$addr" &
  daemon_pid=$!
fi

echo "demo: the field display is at http://$addr/ (open it in a browser with WebGPU)" >&2

viewer_args=(--connect "$addr")
if [ -z "${DISPLAY:-}" ] && [ -z "${WAYLAND_DISPLAY:-}" ]; then
  viewer_args+=(--snapshots "$snapshots" --width 640 --height 480)
  case "$snapshots" in
    /*) shown="$snapshots" ;;
    *) shown="$repo/$snapshots" ;;
  esac
  echo "demo: no display; the viewer writes snapshots of the live model to $shown" >&2
fi
"$bin/texel-viewer" "${viewer_args[@]}" &
viewer_pid=$!

# Whichever ends first ends the demo (Ctrl-C is handled by the trap).
while kill -0 "$daemon_pid" 2>/dev/null && kill -0 "$viewer_pid" 2>/dev/null; do
  sleep 0.5
done
stop
