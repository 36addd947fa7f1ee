#!/usr/bin/env bash
# Install everything simbed + rangemcl need on a fresh Debian machine with Python 3.11:
# the system libraries (Open3D needs libusb; MuJoCo renders headless through EGL), then the project.
#   bash tools/install.sh          # the packages
#   bash tools/install.sh --dev    # plus pytest, hypothesis and ruff
set -euo pipefail
cd "$(dirname "$0")/.."

PY=${PYTHON:-python3}
if ! "$PY" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))'; then
  echo "install.sh: error: Python 3.11 is required, $PY is $("$PY" -V 2>&1)" >&2
  exit 2
fi

SYSTEM_PACKAGES=(libusb-1.0-0 libegl1 libegl-mesa0 libgl1-mesa-dri libgl1 libgomp1)
missing=()
for p in "${SYSTEM_PACKAGES[@]}"; do
  dpkg -s "$p" >/dev/null 2>&1 || missing+=("$p")
done
if [ ${#missing[@]} -gt 0 ]; then
  SUDO=""
  [ "$(id -u)" -ne 0 ] && SUDO="sudo"
  echo "install.sh: installing system packages: ${missing[*]}"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq "${missing[@]}" >/dev/null
fi

extra=""
[ "${1:-}" = "--dev" ] && extra="[dev]"
PIP_ROOT_USER_ACTION=ignore "$PY" -m pip install --disable-pip-version-check -q -e ".${extra}"
"$PY" -c 'import open3d, warp, mujoco, rangemcl, simbed' || { echo "install.sh: error: imports failed after install" >&2; exit 1; }
echo "install.sh: simbed + rangemcl installed for $("$PY" -V)"
