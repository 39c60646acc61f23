#!/usr/bin/env bash
# Make a machine ready: the system packages the console needs (installed with apt when missing), then .venv
# with the console installed in editable mode at the versions of constraints.txt.
#   scripts/bootstrap.sh run    what running needs (make run, simulate, bench, study, depth-library), CRTK and MCAP too
#   scripts/bootstrap.sh test   that and the test stack (make test, make bootstrap)
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}

case "${1:-}" in
  run) extras="[crtk,mcap]" ;;  # the CRTK backend and export --mcap, which make bench measures too
  test) extras="[test]" ;;
  *) echo "usage: scripts/bootstrap.sh run|test" >&2; exit 2 ;;
esac

# Qt's offscreen and xcb platforms load these libraries at run time and pip cannot provide them; pyusb needs
# libusb; Xvfb is the display of `xvfb-run -a make run` on a machine without one.
packages=(libegl1 libgl1 libxkbcommon0 libxkbcommon-x11-0 libfontconfig1 libdbus-1-3 libxcb-cursor0
  libxcb-icccm4 libxcb-keysyms1 libxcb-image0 libxcb-render-util0 libxcb-shape0 libxcb-xinerama0 libusb-1.0-0
  xvfb)
if [ "$1" = test ]; then
  packages+=(hdf5-tools)  # the test that other HDF5 tools read our files
fi

# need: the packages dpkg does not record as installed for this machine's architecture. One query per package
# and no pipe: `ldconfig -p | grep -q` under pipefail reported installed libraries missing (3 runs in 50),
# when grep's exit at the first match broke ldconfig's pipe.
find_missing() {
  local arch package
  arch=$(dpkg --print-architecture)
  need=()
  for package in "${packages[@]}"; do
    [[ $(dpkg-query -W -f='${db:Status-Abbrev}' "$package:$arch" 2>/dev/null) == ii* ]] || need+=("$package")
  done
}

if ! command -v dpkg-query >/dev/null; then
  echo "bootstrap: not a Debian-based system, so its packages are not checked; the console needs what these" \
    "Debian packages hold: ${packages[*]}" >&2
else
  find_missing
  if [ ${#need[@]} -gt 0 ]; then
    if [ "$(id -u)" -eq 0 ]; then
      as_root=()
    elif command -v sudo >/dev/null && sudo -n true 2>/dev/null; then
      as_root=(sudo -n)
    else  # a password prompt in the middle of make is easily missed: say what to run instead
      echo "bootstrap: system packages are missing; install them, then run make again:" >&2
      echo "  sudo apt-get install -y ${need[*]}" >&2
      exit 1
    fi
    echo "bootstrap: installing system packages: ${need[*]}"
    if ! "${as_root[@]}" apt-get update -qq \
      || ! "${as_root[@]}" env DEBIAN_FRONTEND=noninteractive \
        apt-get install -y -qq --no-install-recommends "${need[@]}" >/dev/null; then
      echo "bootstrap: apt-get could not install ${need[*]}" >&2
      exit 1
    fi
    find_missing
    if [ ${#need[@]} -gt 0 ]; then
      echo "bootstrap: apt-get ran, but these are still not installed: ${need[*]}" >&2
      exit 1
    fi
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
