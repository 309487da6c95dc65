#!/usr/bin/env bash
# The open PIC18 toolchain picdrive builds the chip's HEX with:
#   SDCC 4.2.0's pic16 port (compiler sdcc + preprocessor sdcpp, runtime library
#   libsdcc, start-up code crt0*), built from Debian's source package of sdcc
#   (4.2.0+dfsg: Debian's binary package leaves the PIC ports out);
#   gputils (gpasm, gplink, the 18f4431 linker script, p18f4431.inc) and gpsim
#   (cycle-accurate PIC18 core) from Debian's binary packages.
# The source is fetched with `apt-get source` through a private sources list,
# so the machine's apt configuration is not changed.  Only the pic16 port is
# built (about 2 minutes on 2 cores); the result is cached in
#   ${PICDRIVE_TOOLCHAIN:-$HOME/.cache/picdrive/toolchain}/sdcc-4.2.0-pic16
# and this script returns at once when the cache is complete.  The device
# header is not taken from SDCC (the dfsg source has none for the 18F4431):
# picdrive renders it from p18f4431.inc (picdrive.firmware.p18f4431.render_sdcc_device).
set -euo pipefail
ROOT="${PICDRIVE_TOOLCHAIN:-$HOME/.cache/picdrive/toolchain}"
PREFIX="$ROOT/sdcc-4.2.0-pic16"
STAMP="$PREFIX/.complete"
if [ -f "$STAMP" ]; then echo "pic toolchain: cached in $PREFIX"; exit 0; fi

SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
BUILD_DEPS="gputils gpsim dpkg-dev bison flex g++ make libboost-dev zlib1g-dev texinfo"
missing=""
for p in $BUILD_DEPS; do dpkg -s "$p" >/dev/null 2>&1 || missing="$missing $p"; done
if [ -n "$missing" ]; then
  echo "pic toolchain: installing apt packages:$missing"
  $SUDO env DEBIAN_FRONTEND=noninteractive apt-get update -qq
  $SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $missing >/dev/null
fi

WORK="$(mktemp -d "${TMPDIR:-/tmp}/picdrive-sdcc.XXXXXX")"
trap 'rm -rf "$WORK"' EXIT
# A private apt state with the deb-src line of the machine's Debian release.
. /etc/os-release
CODENAME="${VERSION_CODENAME:-bookworm}"
mkdir -p "$WORK/apt/lists/partial"
echo "deb-src http://deb.debian.org/debian $CODENAME main" > "$WORK/apt/sources.list"
APTOPT=(-o "Dir::Etc::SourceList=$WORK/apt/sources.list" -o "Dir::Etc::SourceParts=/dev/null"
        -o "Dir::State::Lists=$WORK/apt/lists" -o "Debug::NoLocking=1")
echo "pic toolchain: fetching Debian's sdcc source package"
apt-get "${APTOPT[@]}" update -qq 2>&1 | grep -v "unsandboxed" || true
(cd "$WORK" && apt-get "${APTOPT[@]}" source -qq sdcc 2>&1 | grep -v "unsandboxed\|^dpkg-source: info" || true)
SRC="$(find "$WORK" -maxdepth 1 -type d -name 'sdcc-*' | head -n 1)"
[ -n "$SRC" ] && [ -x "$SRC/configure" ] || { echo "pic toolchain: apt-get source sdcc gave no source tree" >&2; exit 1; }
case "$SRC" in *4.2.0*) ;; *) echo "pic toolchain: note: sdcc source is $(basename "$SRC"), built as sdcc-4.2.0-pic16" ;; esac

echo "pic toolchain: building the pic16 port (sdcc, sdcpp)"
LOG="$WORK/build.log"
quiet() { "$@" >>"$LOG" 2>&1 || { tail -n 40 "$LOG" >&2; echo "pic toolchain: failed: $*" >&2; exit 1; }; }
PORTS_OFF=""
for port in mcs51 z80 z180 r2k r2ka r3ka sm83 tlcs90 ez80_z80 z80n ds390 ds400 pic14 hc08 s08 stm8 \
            pdk13 pdk14 pdk15 mos6502; do PORTS_OFF="$PORTS_OFF --disable-$port-port"; done
(cd "$SRC" && quiet ./configure --prefix="$PREFIX" $PORTS_OFF --disable-ucsim --disable-device-lib \
    --disable-packihx --disable-sdcdb --disable-sdbinutils --disable-non-free)
JOBS="$(nproc 2>/dev/null || echo 2)"
quiet make -s -C "$SRC/support/cpp" -j"$JOBS"
quiet make -s -C "$SRC/src" -j"$JOBS"

echo "pic toolchain: building the pic16 runtime library and start-up code"
LIBDIR="$SRC/device/lib/pic16"
# The library's automake rules depend on non-free files the dfsg source drops:
# keep autotools from re-running.
NOAUTO=(ACLOCAL=true AUTOCONF=true AUTOMAKE=true AUTOHEADER=true)
(cd "$LIBDIR" && PATH="$SRC/bin:$PATH" quiet ./configure --host=pic16 --build="$(./config.guess)" CC=sdcc)
PATH="$SRC/bin:$PATH" quiet make -s -C "$LIBDIR/libsdcc" -j"$JOBS" "${NOAUTO[@]}"
PATH="$SRC/bin:$PATH" quiet make -s -C "$LIBDIR/startup" -j"$JOBS" "${NOAUTO[@]}"

rm -rf "$PREFIX"
mkdir -p "$PREFIX/bin" "$PREFIX/share/sdcc/include/pic16" "$PREFIX/share/sdcc/lib/pic16"
cp "$SRC/bin/sdcc" "$SRC/bin/sdcpp" "$PREFIX/bin/"
cp "$SRC"/device/include/*.h "$PREFIX/share/sdcc/include/"
cp "$SRC"/device/include/pic16/*.h "$SRC/device/include/pic16/pic16devices.txt" "$PREFIX/share/sdcc/include/pic16/"
cp "$LIBDIR/libsdcc/libsdcc.a" "$PREFIX/share/sdcc/lib/pic16/libsdcc.lib"
cp "$LIBDIR"/startup/crt0.o "$LIBDIR"/startup/crt0i.o "$LIBDIR"/startup/crt0iz.o "$PREFIX/share/sdcc/lib/pic16/"
"$PREFIX/bin/sdcc" -v | head -n 1 > "$PREFIX/VERSION"
touch "$STAMP"
echo "pic toolchain: installed in $PREFIX ($(cat "$PREFIX/VERSION"))"
