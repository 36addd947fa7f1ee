#!/usr/bin/env bash
# A picture of a rerun recording (.rrd) as rerun's own viewer draws it, on a machine without a display
# or a GPU (the viewer picture in docs/recordings.md, "Seeing a run", was made this way):
#
#   bash tools/rrd_screenshot.sh RUN.rrd OUT.png [1400x800]
#
# Needs Xvfb and Mesa's software Vulkan driver (lavapipe):
#   apt-get install -y xvfb xauth mesa-vulkan-drivers libvulkan1
# The viewer's GL backend does not work under Xvfb ("does not support drawing to texture format R32Float"),
# and grabbing its window from the X screen gives a black picture: the viewer's own --screenshot-to is used.
# The screen is larger than the window (drawn at twice its size), so that the pointer, in the screen's
# middle, stays off the window (a hover box otherwise).
# Its usage analytics are switched off in a throw-away HOME.
set -euo pipefail
rrd=$1
png=$2
size=${3:-1400x800}
command -v Xvfb >/dev/null || { echo "rrd_screenshot: needs Xvfb (apt-get install -y xvfb xauth)" >&2; exit 2; }
icd=$(ls /usr/share/vulkan/icd.d/lvp_icd.*.json 2>/dev/null | head -n1)
[ -n "$icd" ] || { echo "rrd_screenshot: needs lavapipe (apt-get install -y mesa-vulkan-drivers libvulkan1)" >&2; exit 2; }
home=$(mktemp -d)
display=:$((90 + RANDOM % 9))
Xvfb "$display" -screen 0 6400x4000x24 -nolisten tcp > "$home/xvfb.log" 2>&1 &
xvfb=$!
trap 'kill $xvfb 2>/dev/null || true; rm -rf "$home"' EXIT
sleep 1
export HOME=$home CI=1 DISPLAY=$display WGPU_BACKEND=vulkan VK_ICD_FILENAMES=$icd
rerun analytics disable > /dev/null 2>&1 || true
timeout 120 rerun "$rrd" --window-size "$size" --screenshot-to "$png" > "$home/viewer.log" 2>&1 < /dev/null \
  || { tail -n 5 "$home/viewer.log" >&2; exit 1; }
echo "wrote $png"
