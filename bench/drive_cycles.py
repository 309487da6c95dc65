"""Drive firmware on the PIC18 core: flash of drive.c / drive_core.c and worst-case
cycles of core_control, core_speed_encoder and the hall-edge path, compiled with
SDCC's pic16 port and timed in gpsim (18F4520 core, same instruction timing).

    PYTHONPATH=$PWD/host python3 bench/drive_cycles.py [firmware folder ...]

Default folder: firmware_build/duy2008.  For each folder it prints the code
bytes of drive.c and drive_core.c (gplink map) and, for a corpus of samples
(rest, a step into the current limit, reversal, saturation, int16 extremes),
the worst cycles of each measured call.  The harness calls the functions from
main(); the figures are the function's own cycles (call to return).  It also
prints the whole speed-loop interrupt over picdrive.gpsim's corpus with and
without the link's link_sample() (the drive's share of the interrupt budget).
"""
import os
import re
import subprocess
import sys
import tempfile
from pathlib import Path

from picdrive.firmware.p18f4431 import render_sdcc_device
from picdrive.firmware.target import SDCC_FLAGS

TC = Path(os.environ.get("PICDRIVE_SDCC", Path.home() / ".cache/picdrive/toolchain/sdcc-4.2.0-pic16"))
LIB = TC / "share/sdcc/lib/pic16"
LKR = "/usr/share/gputils/lkr/18f4431_g.lkr"
#: the image's SDCC options (picdrive.target.SDCC_FLAGS, one place); PICDRIVE_SDCC_OPTS
#: (space-separated) adds options to compare.
EXTRA = list(SDCC_FLAGS[2:]) + os.environ.get("PICDRIVE_SDCC_OPTS", "").split()

# (target, adc, speed state) samples: rest, step into the current limit, reversal,
# saturation, int16 extremes
CORPUS = [(0, 0, 0), (6400, 300, 0), (6400, 700, 1000), (-6400, 100, 6000), (32767, 1023, -32768),
          (-32768, 0, 32767), (100, 650, 17000), (-17000, 20, -200), (17425, 512, 8700), (5, 5, 5)]

HARNESS = r"""
#include <stdint.h>
#include "drive_core.h"
#pragma config WDTEN = OFF
#define cp core_p
#define cs core_s
volatile int16_t sink;
static const int16_t vec[][3] = { %(vec)s };
void mark(void) { }
/* the generic-pointer helpers reference the EEPROM accessors (a device library
   this toolchain does not build); no pointer here points into EEPROM */
void __eeprom_gptrget1(void) { }
void __eeprom_gptrget2(void) { }
void __eeprom_gptrget4(void) { }
void __eeprom_gptrput1(void) { }
void __eeprom_gptrput2(void) { }
void __eeprom_gptrput4(void) { }
void main(void)
{
    uint8_t k, j;
    for (j = 0u; j < CORE_N_RULES; j++) {
        cp.kp[j] = (int16_t)(FW_RULE1_KP + 97 * j); cp.kits[j] = FW_RULE1_KITS; cp.kdts[j] = 3000;
        cp.kc[j] = FW_RULE1_KC;
    }
    cp.premise_lo = FW_PREMISE_LO; cp.premise_hi = FW_PREMISE_HI;
    cp.mu_k = core_premise_k(cp.premise_lo, cp.premise_hi);
    cp.b_q14 = FW_SETPOINT_WEIGHT; cp.u_min = FW_U_MIN; cp.u_max = FW_U_MAX;
    cp.controller = %(controller)du; cp.ilim = 500; cp.accel_step = 0u;
    core_reset();
    for (k = 0u; k < %(n)du; k++) {
        int16_t t = vec[k][0], s = vec[k][2];
        uint16_t a = (uint16_t)vec[k][1];
        cs.speed = s;
        cs.law.integ = (int32_t)s * 3000;
        mark();
        core_control(t, a);
        sink = cs.u;
        mark();
        core_speed_encoder((uint16_t)(cs.pos_prev + (uint16_t)(s >> 6)), (uint16_t)(a * 7u), 0u);
        sink = cs.speed;
        mark();
    }
    for (;;) {
        mark();
    }
}
"""


def sdcc(args, cwd):
    r = subprocess.run([str(TC / "bin/sdcc"), *SDCC_FLAGS[:4],
                        "-I.", *EXTRA, *args], cwd=cwd, capture_output=True, text=True)
    if r.returncode != 0:
        raise SystemExit(f"sdcc {' '.join(args)} failed:\n{r.stderr[-2000:]}")


def section_bytes(obj: Path) -> dict:
    """Bytes of each code and const (initialised program-memory) section of an object (gpvo):
    SDCC puts each function in its own section S_<file>__<function>."""
    out = subprocess.run(["gpvo", str(obj)], capture_output=True, text=True).stdout
    secs = {}
    for blk in out.split("Section Header")[1:]:
        name = re.search(r"Name\s+(\S+)", blk)
        size = re.search(r"Size of Section\s+(\d+)", blk)
        if name and size and ("Executable code" in blk or "ROM data" in blk or "Program memory" in blk):
            secs[re.sub(r"^S_[A-Za-z0-9_]+?__", "", name.group(1))] = int(size.group(1))
    return secs


def code_bytes(obj: Path) -> int:
    """Bytes of the code and const sections of an object."""
    return sum(section_bytes(obj).values())


def size_table(secs: dict, top: int = 12) -> str:
    """The largest sections, one 'bytes name' per line."""
    rows = sorted(secs.items(), key=lambda kv: -kv[1])[:top]
    return "\n".join(f"    {b:6d}  {n}" for n, b in rows)


def measure(folder: Path, controller: int = 1) -> dict:
    with tempfile.TemporaryDirectory(prefix="drivecyc-") as td:
        t = Path(td)
        h, s = render_sdcc_device()
        (t / "xc.h").write_text(h)
        (t / "xc_sfr.c").write_text(s)
        for f in folder.iterdir():
            if f.suffix in (".c", ".h"):
                (t / f.name).write_text(f.read_text())
        vec = ", ".join("{%d, %d, %d}" % v for v in CORPUS)
        (t / "harness.c").write_text(HARNESS % {"vec": vec, "n": len(CORPUS), "controller": controller})
        sizes, funcs = {}, {}
        for src in ("drive_core.c", "drive.c", "harness.c", "xc_sfr.c"):
            if (t / src).exists():
                sdcc(["-c", src], t)
                funcs[src] = section_bytes(t / src.replace(".c", ".o"))
                sizes[src] = sum(funcs[src].values())
        objs = [str(LIB / "crt0i.o"), "harness.o", "drive_core.o", "xc_sfr.o", str(LIB / "libsdcc.lib")]
        r = subprocess.run(["gplink", "-m", "-w", "-s", LKR, "-o", "h.hex", *objs], cwd=t,
                           capture_output=True, text=True)
        if r.returncode != 0:
            raise SystemExit(f"gplink failed:\n{r.stdout}{r.stderr}")
        n_marks = 3 * len(CORPUS) + 1
        stc = ["processor p18f4520", "load s h.cod", "break e _mark"]
        for _ in range(n_marks):
            stc += ["run", "cycles"]
        stc.append("quit")
        (t / "s.stc").write_text("\n".join(stc) + "\n")
        with open(t / "out.txt", "wb") as fo:
            subprocess.run(["gpsim", "-i", "-S", "disable", "-c", "s.stc"], cwd=t, stdout=fo,
                           stderr=subprocess.STDOUT, timeout=300)
        txt = (t / "out.txt").read_bytes().decode("latin-1")
        cyc = [int(x) for x in re.findall(r"(\d+) = 0x[0-9A-F]+\s", txt)]
        if len(cyc) < n_marks:
            raise SystemExit(f"gpsim gave {len(cyc)} of {n_marks} cycle counts")
        law = [cyc[3 * k + 1] - cyc[3 * k] for k in range(len(CORPUS))]
        enc = [cyc[3 * k + 2] - cyc[3 * k + 1] for k in range(len(CORPUS))]
        return {"sizes": sizes, "funcs": funcs, "core_control": law, "core_speed_encoder": enc}


def speed_loop_without_link(folder: Path) -> dict:
    """Worst-case speed-loop interrupt (picdrive.gpsim's corpus, each telemetry mode) of the firmware
    as it is and of a copy whose speed loop does not call link_sample() (the link's telemetry and
    capture sampling): {mode: (whole, without link_sample)}.  The drive's share of the budget."""
    import shutil
    from picdrive.firmware import gpsim
    with tempfile.TemporaryDirectory(prefix="drivenolink-") as td:
        t = Path(td)
        cut = t / "fw"
        shutil.copytree(folder, cut)
        text = (cut / "drive.c").read_text()
        if text.count("    link_sample();\n") != 1:
            raise SystemExit(f"{folder}/drive.c: expected one link_sample() call in the speed loop")
        (cut / "drive.c").write_text(text.replace("    link_sample();\n", ""))
        whole = gpsim.measure_modes(folder, t / "whole")
        drive = gpsim.measure_modes(cut, t / "cut")
    return {m: (whole[m].worst["speed_loop_isr"], drive[m].worst["speed_loop_isr"]) for m in whole}


def main(argv):
    folders = [Path(a) for a in argv] or [Path("firmware_build/duy2008")]
    for f in folders:
        for mode, (whole, drive) in speed_loop_without_link(f).items():
            print(f"{f}  speed-loop interrupt, telemetry {mode}: {whole} cycles, {drive} without link_sample()")
        for ctl in (1, 0):
            m = measure(f, ctl)
            print(f"{f}  controller={ctl}")
            print(f"  flash bytes: drive_core.c {m['sizes']['drive_core.c']}, drive.c {m['sizes'].get('drive.c')}")
            if ctl == 1:
                for src in ("drive_core.c", "drive.c"):
                    if src in m["funcs"]:
                        print(f"  largest functions of {src} (bytes):\n{size_table(m['funcs'][src])}")
            for k in ("core_control", "core_speed_encoder"):
                print(f"  {k:20s} worst {max(m[k]):6d} cycles  best {min(m[k]):6d}  ({m[k]})")


if __name__ == "__main__":
    main(sys.argv[1:])
