#!/usr/bin/env python3
"""Firmware figures: RAM of the globals and buffers against the PIC18F4431's 768 B,
a flash estimate, the bit-exact check on 10^5 vectors, the closed-loop comparison.

RAM and flash come from the host build compiled with avr-gcc (a compiler whose
``int`` is 16 bits, like XC8's): ``avr-nm -S`` sizes of every .data/.bss symbol
of drive.c, drive_core.c and link_fw.c.  These are the sizes of the C objects
with 16-bit ints and 8-bit chars, which is what XC8 allocates for them too
(XC8 adds its own compiled stack for locals and interrupt context saving,
which this does not count).  The flash figure is AVR code size: an estimate of
the code's bulk, NOT a PIC18 figure.

Usage:
  python3 bench/firmware.py                  # figures for firmware_build/duy2008/
  python3 bench/firmware.py --folder DIR     # another generated folder
  python3 bench/firmware.py --regenerate     # regenerate firmware_build/duy2008/ from
                                             # examples/duy2008.fuzzy-hinf.design.json first
  python3 bench/firmware.py --vectors N      # bit-exact vectors per function (default 100000)
"""
from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from picdrive.firmware import codegen, fixedpoint
from picdrive.paths import firmware_build_dir, repo_root
from picdrive.profile import load_profile
from picdrive.result import load_design

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from support import core_c  # noqa: E402  (the gcc/ctypes harness of the bit-exact model)
from support.fixed_loop import closed_loop_compare, measurement_lag_effect  # noqa: E402

RAM_BYTES = 768
RAM_TARGET = 600


def ram_and_flash(folder: Path) -> tuple[dict, dict, list]:
    hb = codegen.host_build(folder)
    tmp = Path(tempfile.mkdtemp(prefix="picdrive-avr-"))
    ram, flash, syms = {}, {}, []
    for src in hb["sources"]:
        obj = tmp / (Path(src).stem + ".o")
        subprocess.run(["avr-gcc", "-mmcu=atmega328p", "-Os", *hb["cflags"],
                        *[f"-I{d}" for d in hb["include_dirs"]], "-c", src, "-o", str(obj)],
                       check=True, capture_output=True, text=True)
        nm = subprocess.run(["avr-nm", "-S", "--size-sort", str(obj)], check=True, capture_output=True,
                            text=True).stdout
        total = 0
        for line in nm.splitlines():
            parts = line.split()
            if len(parts) == 4 and parts[2] in ("b", "B", "d", "D", "C"):   # .bss, .data, common
                size = int(parts[1], 16)
                total += size
                syms.append((size, Path(src).name, parts[3]))
        ram[Path(src).name] = total
        size = subprocess.run(["avr-size", "-A", str(obj)], check=True, capture_output=True, text=True).stdout
        text = sum(int(l.split()[1]) for l in size.splitlines() if l.startswith((".text", ".progmem", ".rodata")))
        flash[Path(src).name] = text
    return ram, flash, sorted(syms, reverse=True)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--folder", default=str(firmware_build_dir() / "duy2008"))
    ap.add_argument("--profile", default="duy2008")
    ap.add_argument("--design", default=str(repo_root() / "examples" / "duy2008.fuzzy-hinf.design.json"))
    ap.add_argument("--regenerate", action="store_true")
    ap.add_argument("--vectors", type=int, default=100_000)
    a = ap.parse_args()
    prof = load_profile(a.profile)
    folder = Path(a.folder)
    fw = codegen.generate(prof, a.design)
    if a.regenerate:
        codegen.write_firmware(fw, folder, hex_build=True)   # the HEX too: it fits the chip
        print(f"regenerated {folder}")
    print("== what the generator chose")
    for line in fw.summary:
        print("  " + line)

    print("\n== RAM of globals and buffers (avr-gcc, 16-bit int; avr-nm sizes of .data/.bss)")
    ram, flash, syms = ram_and_flash(folder)
    for k, v in ram.items():
        print(f"  {k:<14} {v:5d} B")
    total = sum(ram.values())
    print(f"  {'total':<14} {total:5d} B of {RAM_BYTES} B ({100 * total / RAM_BYTES:.0f} %), target <= {RAM_TARGET} B: "
          f"{'MET' if total <= RAM_TARGET else 'MISSED'}")
    print("  largest:")
    for size, f, name in syms[:12]:
        print(f"    {size:4d} B  {f:<14} {name}")
    print("\n== flash (AVR code size: an estimate of bulk, not a PIC18 figure)")
    for k, v in flash.items():
        print(f"  {k:<14} {v:6d} B")
    print(f"  {'total':<14} {sum(flash.values()):6d} B (PIC18F4431 has 16384 B)")

    print(f"\n== bit-exact: C (gcc) vs picdrive.firmware.fixedpoint on {a.vectors} random vectors per function")
    lib = core_c.build_core_lib(folder)
    t0 = time.perf_counter()
    res = core_c.compare_with_c(fw.plan, lib, a.vectors, seed=2024)
    dt = time.perf_counter() - t0
    for k, v in res.items():
        print(f"  {k:<10} {v['vectors']:8d} vectors, {v['mismatches']} mismatches")
    print(f"  ({dt:.1f} s)")
    if res["total"]["mismatches"]:
        print("  first mismatch:", res["total"]["first"])

    print("\n== closed loop on the DC-equivalent plant (1 s: speed step, load step at 0.5 s)")
    print("   arithmetic: fixed-point law vs law_step on the same (instant) speed sample, limit 0.5 %")
    print("   with sensors: the firmware's measurements (encoder M/T + half-sample extrapolation, bus shunt,")
    print("   10-bit ADC, PDC counts) vs law_step on the true speed -- a sensor effect, not arithmetic")
    from picdrive.firmware import pcpwm
    for pname in ("duy2008", "assawinchaichote2016"):
        p = load_profile(pname)
        for method in ("fuzzy-hinf", "mixed-pid", "zn"):
            path = repo_root() / "examples" / f"{pname}.{method}.design.json"
            try:
                law = load_design(path, require_usable=True, profile=p).law
            except Exception as e:
                print(f"  {pname:<22} {method:<11} skipped: {e}")
                continue
            plan = fixedpoint.plan_fixed_point(p, law, pcpwm.plan_pwm(p))
            ra = closed_loop_compare(p, law, plan, measurement="instant")
            rs = closed_loop_compare(p, law, plan, measurement="firmware")
            lag = measurement_lag_effect(p, law)
            print(f"  {pname:<22} {method:<11} arithmetic RMS {100 * ra['rms_dev']:.4f} % (max {100 * ra['max_dev']:.3f} %)"
                  f" {'OK' if ra['rms_dev'] <= 0.005 else 'OVER'};  with sensors RMS {100 * rs['rms_dev']:.3f} % "
                  f"(max {100 * rs['max_dev']:.2f} %);  float law, sample-average vs instant speed: "
                  f"RMS {100 * lag['rms_dev']:.3f} %")
    return 0 if total <= RAM_TARGET and not res["total"]["mismatches"] else 1


if __name__ == "__main__":
    sys.exit(main())
