#!/usr/bin/env bash
# Installs everything picdrive needs on a fresh Debian machine with Python 3.11:
#   apt: gputils (Microchip's p18f4431.inc; gpasm), gpsim (the PIC18 simulator test), gcc-avr + avr-libc (a 16-bit-int C
#        compiler that catches XC8 integer-promotion bugs on the host), gcc
#   pip: picdrive itself (editable) with its test dependencies
# Safe to run again; it skips what is already there.
set -euo pipefail
cd "$(dirname "$0")/.."
APT_PKGS="gputils gpsim gcc-avr avr-libc gcc make"
missing=""
for p in $APT_PKGS; do dpkg -s "$p" >/dev/null 2>&1 || missing="$missing $p"; done
if [ -n "$missing" ]; then
  SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
  echo "setup: installing apt packages:$missing"
  $SUDO env DEBIAN_FRONTEND=noninteractive apt-get update -qq
  $SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $missing >/dev/null
fi
echo "setup: installing picdrive (pip install -e '.[dev]')"
python3 -m pip install -q --disable-pip-version-check -e '.[dev]'
# pyenv puts console scripts behind shims that appear only after a rehash
if command -v pyenv >/dev/null 2>&1; then pyenv rehash || true; fi
echo "setup: done"
