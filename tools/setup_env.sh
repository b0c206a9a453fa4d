#!/usr/bin/env bash
# Set up everything frslam needs on a fresh Debian/Ubuntu machine with python3 and apt:
# the system library open3d needs (libusb-1.0-0, libgomp1), a virtual environment in .venv,
# and the package with its dev extra (editable). Idempotent: re-running is quick.
#
# Quiet: one line per stage; apt's and pip's output goes to .venv/setup.log. On a failure the
# log's last lines and its path are printed, and the exit code is non-zero.
set -euo pipefail
cd "$(dirname "$0")/.."

LOG=.venv/setup.log
mkdir -p .venv
: >"$LOG"

stage() { printf 'setup: %s\n' "$1"; }

# run "what" cmd...: the command's output to the log; on failure the log's tail and path, exit 1
run() {
  local what=$1
  shift
  printf '\n$ %s\n' "$*" >>"$LOG"
  if ! "$@" >>"$LOG" 2>&1; then
    printf 'setup: %s failed; the last lines of %s:\n' "$what" "$LOG" >&2
    tail -n 25 "$LOG" | sed 's/^/  /' >&2
    printf 'setup: full log: %s\n' "$(pwd)/$LOG" >&2
    exit 1
  fi
}

need_apt=()
for lib in libusb-1.0.so.0 libgomp.so.1; do
  if ! ldconfig -p 2>/dev/null | grep -q "$lib"; then need_apt+=("$lib"); fi
done
PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ] && ! "$PY" -c "import ensurepip" >/dev/null 2>&1; then
  need_apt+=(python3-venv)
fi
if [ ${#need_apt[@]} -gt 0 ]; then
  stage "system libraries (apt: libusb-1.0-0 libgomp1 python3-venv)"
  SUDO=""
  [ "$(id -u)" -ne 0 ] && SUDO="sudo"
  run "apt-get update" $SUDO apt-get update -qq
  run "apt-get install" $SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq \
    libusb-1.0-0 libgomp1 python3-venv
fi

if [ ! -x .venv/bin/python ]; then
  stage "virtual environment (.venv)"
  run "creating .venv" "$PY" -m venv .venv
fi
stage "pip"
run "upgrading pip" .venv/bin/python -m pip install --upgrade pip
stage "frslam and its dependencies (pip install -e .[dev]; a few minutes the first time)"
run "installing frslam" .venv/bin/python -m pip install -e ".[dev]"
stage "checking the imports"
run "importing frslam_graph, open3d, gtsam, kiss_icp, cv2" \
  .venv/bin/python -c "import frslam_graph, open3d, gtsam, kiss_icp, cv2"
stage "ready: .venv/bin/frslam (log: $LOG)"
