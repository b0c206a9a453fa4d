#!/usr/bin/env bash
# Set up everything frslam needs on a fresh Debian/Ubuntu machine with python3 and apt:
# the system library open3d needs (libusb-1.0-0, libgomp1), a virtual environment in .venv,
# and the package with its dev extra (editable). Idempotent: re-running is quick.
set -euo pipefail
cd "$(dirname "$0")/.."

need_apt=()
for lib in libusb-1.0.so.0 libgomp.so.1; do
  if ! ldconfig -p 2>/dev/null | grep -q "$lib"; then need_apt+=("$lib"); fi
done
if [ ${#need_apt[@]} -gt 0 ]; then
  SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq libusb-1.0-0 libgomp1 python3-venv >/dev/null
fi

PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  "$PY" -m venv .venv
fi
.venv/bin/python -m pip install -q --upgrade pip 2>&1 | grep -v "^WARNING: Location" || true
.venv/bin/python -m pip install -q -e ".[dev]" 2>&1 | grep -v "^WARNING: Location" || true
.venv/bin/python -c "import frslam_graph, open3d, gtsam, kiss_icp, cv2" \
  || { echo "setup_env.sh: the environment is incomplete (see pip output above)" >&2; exit 1; }
