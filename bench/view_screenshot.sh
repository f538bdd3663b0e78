#!/usr/bin/env bash
# The README's screenshot of a `sonarset view` recording (docs/view/viewer.png), as the real Rerun
# desktop viewer shows it, rendered in software on a machine without a GPU or a display:
# Xvfb + Mesa's lavapipe (llvmpipe Vulkan), driven with xdotool, captured with ImageMagick.
#
#   bash bench/view_screenshot.sh                   # from the repository root (as root: apt-get)
#   PNG=/tmp/viewer.png SKIP_APT=1 bash bench/view_screenshot.sh
#
# The clicks are screen coordinates for a 1600x1000 screen and this one-minute recording
# (rerun 0.41.0): pause, put the time cursor at about +30 s, unselect, hide the selection panel.
set -eu
W=${W:-/tmp/view-shot}
PNG=${PNG:-docs/view/viewer.png}
DISP=${DISP:-:99}
mkdir -p "$W" "$(dirname "$PNG")"

# 1. Debian packages: a virtual X server, Mesa's software Vulkan/GL, xdotool, ImageMagick.
if [ -z "${SKIP_APT:-}" ]; then
  apt-get update -qq
  DEBIAN_FRONTEND=noninteractive apt-get install -y -q \
    xvfb mesa-vulkan-drivers libgl1-mesa-dri libegl1 x11-utils xdotool imagemagick >/dev/null
fi

# 2. A one-minute lab run and its recording with EchoPT's 3-step predictions.
rm -rf "$W/view1.zarr"
(cd "$W" && sonarset generate view1.zarr --world lab --runs 1 --minutes 1 --test-runs 0 --seed 5)
sonarset view "$W/view1.zarr" --run run_000 --model echopt:pretrained --horizon 3 --out "$W/view1.rrd"

# 3. Xvfb without the Composite extension: with it, the viewer asks for a transparent (32-bit)
#    window that stays black under lavapipe; without it, it falls back to an opaque one.
#    (WGPU_BACKEND=gl does not work: llvmpipe GL cannot draw to R32Float.)
Xvfb "$DISP" -screen 0 1600x1000x24 -nolisten tcp -extension Composite >"$W/xvfb.log" 2>&1 &
XVFB=$!
export DISPLAY=$DISP
RERUN=
trap 'if [ -n "$RERUN" ]; then pkill -P "$RERUN"; kill "$RERUN"; fi; kill "$XVFB"; true' EXIT
sleep 2
mkdir -p "$W/xdg" && chmod 700 "$W/xdg"
RERUN_ANALYTICS=0 XDG_RUNTIME_DIR="$W/xdg" rerun "$W/view1.rrd" >"$W/rerun.log" 2>&1 &
RERUN=$!
sleep 60                                   # load the 7 MB recording (software rendering is slow)

# 4. Pause, scrub to ~+30 s, unselect, hide the right panel. Software frames are slow, so each
#    click is a move, a pause, then the click.
click() { xdotool mousemove "$1" "$2"; sleep 1; xdotool click 1; sleep 3; }
click 28 764                               # the play/pause button
click 892 880                              # the streams' time area at ~+30 s (selects a row)
xdotool windowfocus "$(xdotool search --name '^Rerun$' | head -1)"
sleep 1
xdotool key Escape                         # unselect
sleep 2
click 1442 18                              # toggle the selection panel off
xdotool mousemove 1100 18                  # park the pointer on the empty top bar
sleep 5
import -window root "$W/raw.png"

# 5. Optimized PNG (about 200 KB at 1600x1000).
python - "$W/raw.png" "$PNG" <<'EOF'
import os, sys
from PIL import Image
im = Image.open(sys.argv[1]).convert("RGB")
im.save(sys.argv[2], optimize=True)
print(sys.argv[2], im.size, os.path.getsize(sys.argv[2]) // 1024, "KB")
EOF
rerun --version | head -1
