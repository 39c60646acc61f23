#!/usr/bin/env bash
# Make a fresh machine ready: the system libraries Qt needs, Xvfb and the HDF5 tools (when missing), and
# .venv with the console installed in editable mode at the versions of constraints.txt.
#   scripts/bootstrap.sh run    what running needs (make run, simulate, bench, study, depth-library)
#   scripts/bootstrap.sh test   that and the test stack (make test, make bootstrap)
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}

case "${1:-}" in
  run) extras="" ;;
  test) extras="[test]" ;;
  *) echo "usage: scripts/bootstrap.sh run|test" >&2; exit 2 ;;
esac

# Qt's offscreen and xcb platforms load these at run time; pip cannot provide them.
need=()
have_lib() { ldconfig -p 2>/dev/null | grep -q "$1"; }
have_lib libEGL.so.1 || need+=(libegl1)
have_lib libGL.so.1 || need+=(libgl1)
have_lib libxkbcommon.so.0 || need+=(libxkbcommon0)
have_lib libxkbcommon-x11.so.0 || need+=(libxkbcommon-x11-0)
have_lib libfontconfig.so.1 || need+=(libfontconfig1)
have_lib libdbus-1.so.3 || need+=(libdbus-1-3)
have_lib libxcb-cursor.so.0 || need+=(libxcb-cursor0)
have_lib libxcb-icccm.so.4 || need+=(libxcb-icccm4)
have_lib libxcb-keysyms.so.1 || need+=(libxcb-keysyms1)
have_lib libxcb-image.so.0 || need+=(libxcb-image0)
have_lib libxcb-render-util.so.0 || need+=(libxcb-render-util0)
have_lib libxcb-shape.so.0 || need+=(libxcb-shape0)
have_lib libxcb-xinerama.so.0 || need+=(libxcb-xinerama0)
have_lib libusb-1.0.so.0 || need+=(libusb-1.0-0)
command -v Xvfb >/dev/null || need+=(xvfb)
command -v h5dump >/dev/null || need+=(hdf5-tools)  # the test that other HDF5 tools read our files
if [ ${#need[@]} -gt 0 ]; then
  echo "bootstrap: installing system packages: ${need[*]}"
  SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
  if ! { $SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${need[@]}"; } >/dev/null; then
    echo "bootstrap: could not install ${need[*]}; install them with your package manager" >&2
    exit 1
  fi
fi

# The stamps hold what .venv was installed from; .installed-test covers make run's needs too.
inputs=$(sha256sum pyproject.toml constraints.txt)
installed_from_these() { [ -x .venv/bin/python ] && [ -f "$1" ] && [ "$(<"$1")" = "$inputs" ]; }
if installed_from_these .venv/.installed-test || { [ "$1" = run ] && installed_from_these .venv/.installed-run; }; then
  exit 0
fi
if ! installed_from_these .venv/.installed-run; then
  # new, or installed from other pins: made afresh, so that no package the pins no longer name stays behind
  "$PY" -m venv --clear .venv
fi
.venv/bin/python -m pip install -q --upgrade pip
.venv/bin/python -m pip install -q -c constraints.txt -e ".$extras"
printf '%s\n' "$inputs" >".venv/.installed-$1"
