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

from picdrive.p18f4431 import render_sdcc_device
from picdrive.target import SDCC_FLAGS

TC = Path(os.environ.get("PICDRIVE_SDCC", Path.home() / ".cache/picdrive/toolchain/sdcc-4.2.0-pic16"))
LIB = TC / "share/sdcc/lib/pic16"
LKR = "/usr/share/gputils/lkr/18f4431_g.lkr"
#: the arithmetic check's harness (32 constant shifts written out) outgrows the 4431's 16 kB: it is
#: linked into the 18F4520's 32 kB, the core gpsim runs
LKR_CHECK = "/usr/share/gputils/lkr/18f4520_g.lkr"
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


PRODUCTS = r"""
#include <stdint.h>
#include "drive_core.h"
#pragma config WDTEN = OFF
void ok(void) { }
void bad(void) { }
%(stubs)s
void main(void)
{
    uint16_t x = 12345u, y = 54321u, k;
    uint32_t ss = 0u, su = 0u, sr = 0u, sl = 0u;
    for (k = 0u; k < %(n)du; k++) {
        x = (uint16_t)(x * 25173u + 13849u);
        y = (uint16_t)(y * 16807u + 12345u);
        if (k == 0u) { x = 0x8000u; y = 0x8000u; }
        if (k == 1u) { x = 0xFFFFu; y = 0x8000u; }
        if (k == 2u) { x = 0xFFFFu; y = 0xFFFFu; }
        if (k == 3u) { x = 0x8000u; y = 0u; }
        ss = ss * 31u + (uint32_t)CORE_MULS((int16_t)x, (int16_t)y);
        su = su * 31u + CORE_MULU(x, y);
        core_sh.x = (int32_t)(((uint32_t)x << 16) | y);
        core_sh.n = (uint8_t)(k & 31u);
        core_asr_asm();
        sr = sr * 31u + (uint32_t)core_sh.x;
        core_sh.x = (k & 32u) ? (int32_t)(int16_t)y : (int32_t)(((uint32_t)x << 16) | y);
        core_sh.n = (uint8_t)(k & 31u);
        sl = sl * 31u + (uint32_t)core_shl_sat();
        {
            int32_t v = (int32_t)(((uint32_t)x << 16) | y);
%(asr_consts)s
        }
    }
    if (ss == %(ss)sUL && su == %(su)sUL && sr == %(sr)sUL && sl == %(sl)sUL) { ok(); } else { bad(); }
    for (;;) { }
}
"""


def expected_products(n):
    """The host's checksums of the same product sequence (Python integers)."""
    x, y, ss, su, sr, sl = 12345, 54321, 0, 0, 0, 0
    sat = lambda v, b: min(max(v, -2**(b - 1)), 2**(b - 1) - 1)  # noqa: E731
    for k in range(n):
        x = (x * 25173 + 13849) & 0xFFFF
        y = (y * 16807 + 12345) & 0xFFFF
        x, y = {0: (0x8000, 0x8000), 1: (0xFFFF, 0x8000), 2: (0xFFFF, 0xFFFF), 3: (0x8000, 0)}.get(k, (x, y))
        sx, sy = x - (x >> 15 << 16), y - (y >> 15 << 16)
        ss = (ss * 31 + (sx * sy)) & 0xFFFFFFFF
        su = (su * 31 + x * y) & 0xFFFFFFFF
        xy = (x << 16) | y
        xy -= (xy >> 31) << 32
        sr = (sr * 31 + (xy >> (k & 31))) & 0xFFFFFFFF               # Python >> is floor
        v = sy if k & 32 else xy
        sl = (sl * 31 + sat(v << (k & 31), 32)) & 0xFFFFFFFF
        for c in ASR_COUNTS:
            sr = (sr * 31 + (xy >> c)) & 0xFFFFFFFF
    return ss, su, sr, sl


#: drive_core.h's portable CORE_ASR (drive.c's form) by each constant count, folded into the same sum
#: as core_asr_asm.  Count 15 is left out: SDCC 4.2 pic16 miscompiles a 32-bit `>> 15` whose result
#: reuses the operand's registers (it overwrites byte 1 before taking its bit 7; this check found it,
#: and it hit CORE_SHIFT_KB in core_control before drive_core.c moved to core_asr_asm); drive.c
#: shifts by CORE_QI - CORE_QU only.
ASR_COUNTS = [c for c in range(32) if c != 15]
ASR_CONSTS = "\n".join(f"            sr = sr * 31u + (uint32_t)CORE_ASR(v, {c});" for c in ASR_COUNTS)


def check_products(folder: Path, n: int = 3000) -> bool:
    """CORE_MULS / CORE_MULU, the shifts core_asr_asm / core_shl_sat and CORE_ASR by the constant
    counts 0..31 but 15 (ASR_COUNTS) on the PIC18 core (gpsim) against exact results (floor division, saturated
    product): True if equal."""
    ss, su, sr, sl = expected_products(n)
    stubs = "\n".join(f"void __eeprom_gptr{k}(void) {{ }}" for k in
                      ("get1", "get2", "get4", "put1", "put2", "put4"))
    with tempfile.TemporaryDirectory(prefix="drivemul-") as td:
        t = Path(td)
        h, s = render_sdcc_device()
        (t / "xc.h").write_text(h)
        (t / "xc_sfr.c").write_text(s)
        for f in ("drive_core.c", "drive_core.h", "drive_params.h"):
            (t / f).write_text((folder / f).read_text())
        (t / "mc.c").write_text(PRODUCTS % {"n": n, "ss": f"0x{ss:08X}", "su": f"0x{su:08X}", "sr": f"0x{sr:08X}",
                                     "sl": f"0x{sl:08X}", "stubs": stubs,
                                     "asr_consts": ASR_CONSTS})
        for src in ("mc.c", "drive_core.c", "xc_sfr.c"):
            sdcc(["-c", src], t)
        subprocess.run(["gplink", "-m", "-w", "-s", LKR_CHECK, "-o", "mc.hex", str(LIB / "crt0i.o"), "mc.o",
                        "drive_core.o", "xc_sfr.o", str(LIB / "libsdcc.lib")], cwd=t, check=True,
                       capture_output=True)
        (t / "s.stc").write_text("processor p18f4520\nload s mc.cod\nbreak e _ok\nbreak e _bad\n"
                                 "break c 200000000\nrun\nquit\n")
        with open(t / "out.txt", "wb") as fo:
            subprocess.run(["gpsim", "-i", "-S", "disable", "-c", "s.stc"], cwd=t, stdout=fo,
                           stderr=subprocess.STDOUT, timeout=300)
        txt = (t / "out.txt").read_bytes().decode("latin-1")
        m = {}
        for line in (t / "mc.map").read_text().splitlines():
            p = line.split()
            if len(p) >= 3 and p[0] in ("_ok", "_bad"):
                m[p[0]] = int(p[1], 16)
        hit = re.findall(r"Execution at [^(]*\((0x[0-9a-f]+)\)", txt)
        return bool(hit) and int(hit[0], 16) == m["_ok"]


def speed_loop_without_link(folder: Path) -> dict:
    """Worst-case speed-loop interrupt (picdrive.gpsim's corpus, each telemetry mode) of the firmware
    as it is and of a copy whose speed loop does not call link_sample() (the link's telemetry and
    capture sampling): {mode: (whole, without link_sample)}.  The drive's share of the budget."""
    import shutil
    from picdrive import gpsim
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
