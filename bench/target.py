#!/usr/bin/env python3
"""The firmware on the PIC18F4431: flash, RAM + stack and worst-case cycles, today's build beside the baseline.

For each bundled design (examples/*.design.json) and each telemetry mode
(off / 4 signals / 4 signals + a capture armed), prints:
flash, static RAM + worst-case stack (picdrive.firmware.target: SDCC pic16 + gplink,
stack from the call graph), and the worst-case cycles (picdrive.firmware.gpsim, over
the corpus: rest, a step into the current limit, reversal, saturation, int16
extremes) of the speed-loop interrupt (and % of its 1 ms period at 10 MIPS),
the hall interrupt, the UART receive interrupt per byte and link_poll per
maximum-length frame.

The baseline is the firmware as commit c0631cc generated it (before the
8-bit rewrite): its host/ and firmware_templates/ are taken from git at run
time (``git archive c0631cc``, so this needs the repository's history) and its
own ``picdrive firmware`` renders the C; bench/baseline_main_sdcc.c is the
SDCC vector file a new user would write for it (plain ``__interrupt``
handlers, no table-pointer save).  The baseline does not fit the 18F4431's
16 KB: it is linked with picdrive.firmware.target.enlarged_lkr() for measurement
(marked '*').  Timing runs on gpsim's 18F4620 (see picdrive.firmware.gpsim).

Usage:
  python3 bench/target.py                 # all six designs, today and baseline
  python3 bench/target.py --design duy2008.fuzzy-hinf --no-baseline
  python3 bench/target.py --no-baseline --reference-feedforward   # also each design with the
      # reference feedforward compiled in ("today+ff": control.reference_feedforward, the DC gain)
  python3 bench/target.py --no-baseline --identify   # also each design's identification build
      # ("today+id": picdrive firmware --identify)

A design whose profile takes the speed from the halls is also built with the halls on the
input-capture pins ("today-ic", picdrive firmware --hall-input ic) beside the default INT0..INT2;
the last table lists every build side by side against the budgets.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path

from picdrive.firmware import codegen, gpsim, target
from picdrive.paths import repo_root
from picdrive.profile import load_profile

BASELINE_COMMIT = "c0631cc"
HERE = Path(__file__).resolve().parent


def generate_new(design: Path, out: Path, reference_ff: bool = False, hall_input: str = "auto",
                 identify: bool = False) -> tuple[Path, str]:
    profile = load_profile(json.loads(design.read_text())["profile"]["name"])
    if reference_ff:                # the design's law with the reference feedforward's gain set
        import dataclasses
        from picdrive.design.verify import with_reference_ff
        from picdrive.result import load_design, save_design
        res = load_design(str(design))
        res = dataclasses.replace(res, law=with_reference_ff(profile, res.law))
        out.parent.mkdir(parents=True, exist_ok=True)
        design = save_design(res, out.parent / "ff.design.json")
    fw = codegen.generate(profile, design, hall_input=hall_input, identify=identify)
    codegen.write_firmware(fw, out)
    return out, fw.name


def baseline_tree(work: Path) -> Path:
    """host/, firmware_templates/ and examples/ of BASELINE_COMMIT, extracted under ``work``."""
    root = work / "baseline"
    if not root.is_dir():
        root.mkdir(parents=True)
        tar = work / "baseline.tar"
        with open(tar, "wb") as f:
            subprocess.run(["git", "-C", str(repo_root()), "archive", BASELINE_COMMIT, "host", "firmware_templates",
                            "examples"], stdout=f, check=True)
        with tarfile.open(tar) as t:
            t.extractall(root)
    return root


def generate_baseline(design: Path, out: Path, work: Path) -> tuple[Path, str]:
    root = baseline_tree(work)
    profile = json.loads(design.read_text())["profile"]["name"]
    env = dict(os.environ, PYTHONPATH=str(root / "host"))
    subprocess.run([sys.executable, "-m", "picdrive", "firmware", "--profile", profile, "--design",
                    str(root / "examples" / design.name), "-o", str(out)], env=env, check=True,
                   capture_output=True, cwd=root)
    (out / "main_sdcc.c").write_text((HERE / "baseline_main_sdcc.c").read_text())
    return out, profile


BASELINE_PACKAGE = "picdrive_baseline"


def import_baseline(root: Path) -> str:
    """The baseline revision's picdrive, importable as ``picdrive_baseline`` (its codec frames its protocol)."""
    import importlib.util
    if BASELINE_PACKAGE not in sys.modules:
        pkg = root / "host" / "picdrive"
        spec = importlib.util.spec_from_file_location(BASELINE_PACKAGE, pkg / "__init__.py",
                                                      submodule_search_locations=[str(pkg)])
        mod = importlib.util.module_from_spec(spec)
        sys.modules[BASELINE_PACKAGE] = mod
        spec.loader.exec_module(mod)
    return BASELINE_PACKAGE


def measure(folder: Path, name: str, work: Path, protocol_package: str = "picdrive.link") -> tuple[target.Build, dict]:
    b = target.build_measured(folder, work / "hex", name=name)
    return b, gpsim.measure_modes(folder, work / "timing", protocol_package=protocol_package)


def _row(label, b, c, period):
    sl = c.worst["speed_loop_isr"]
    ram = "?" if b.ram_stack_bytes is None else f"{b.ram_bytes}+{b.stack_bytes}={b.ram_stack_bytes}"
    return (f"  {label:<9} {b.flash_bytes:>7,}{'*' if not b.on_chip else ' '} {ram:>15}  {sl:>7,} {100 * sl / period:5.1f} %"
            f"  {c.worst['hall_isr']:>6,}  {c.worst['uart_rx_byte']:>6,}  {c.worst['link_poll_max_frame']:>7,}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--design", action="append", help="design stem (e.g. duy2008.fuzzy-hinf); default all")
    ap.add_argument("--no-baseline", action="store_true", help="skip today's-build-before-the-rewrite baseline")
    ap.add_argument("--reference-feedforward", action="store_true",
                    help="also measure each design with the reference feedforward compiled in (today+ff)")
    ap.add_argument("--identify", action="store_true",
                    help="also measure each design's identification build (today+id: picdrive firmware --identify)")
    a = ap.parse_args()
    designs = sorted((repo_root() / "examples").glob("*.design.json"))
    if a.design:
        designs = [d for d in designs if d.name.removesuffix(".design.json") in a.design]
    B = target.BUDGETS
    period = target.FCY_HZ // B.speed_loop_hz
    print(f"PIC18F4431 at {target.FCY_HZ / 1e6:.0f} MIPS; budgets: flash <= {B.flash_bytes:,} B, RAM + stack <= "
          f"{B.ram_stack_bytes} B, speed loop <= {B.speed_loop_cycles:,} cycles ({B.speed_loop_fraction:.0%} of "
          f"{period:,}), hall <= {B.hall_isr_cycles}, UART RX <= {B.uart_rx_cycles} per byte")
    print("cycles: worst over the corpus, interrupt entry included; '*' = does not fit, linked with an enlarged "
          "script for measurement\n")
    head = (f"  {'build':<9} {'flash B':>8} {'RAM+stack B':>15}  {'speed-loop ISR':>15}  {'hall':>6}  {'UART rx':>6}"
            f"  {'link_poll':>7}")
    summary = []
    with tempfile.TemporaryDirectory(prefix="bench-target-") as t:
        work = Path(t)
        for d in designs:
            stem = d.name.removesuffix(".design.json")
            runs = {}
            folder, name = generate_new(d, work / stem / "new" / "fw")
            runs["today"] = measure(folder, name, work / stem / "new")
            hall_speed = load_profile(json.loads(d.read_text())["profile"]["name"]).sensors.speed_source == "hall"
            if hall_speed:       # the halls on the input-capture pins too (without an encoder they may be)
                folder, name = generate_new(d, work / stem / "ic" / "fw", hall_input="ic")
                runs["today-ic"] = measure(folder, name, work / stem / "ic")
            if a.reference_feedforward:
                folder, name = generate_new(d, work / stem / "ff" / "fw", reference_ff=True)
                runs["today+ff"] = measure(folder, name, work / stem / "ff")
            if a.identify:
                folder, name = generate_new(d, work / stem / "id" / "fw", identify=True)
                runs["today+id"] = measure(folder, name, work / stem / "id")
            if not a.no_baseline and (baseline_tree(work) / "examples" / d.name).is_file():
                folder, name = generate_baseline(d, work / stem / "base" / "fw", work)
                runs["baseline"] = measure(folder, name, work / stem / "base",
                                           protocol_package=import_baseline(baseline_tree(work)))
            for mode in gpsim.TELEMETRY_MODES:
                print(f"{stem}, telemetry {mode}")
                print(head)
                for label in ("baseline", "today", "today-ic", "today+ff", "today+id"):
                    if label in runs:
                        b, cm = runs[label]
                        print(_row(label, b, cm[mode], period))
                if "baseline" in runs:
                    (b0, c0), (b1, c1) = runs["baseline"], (runs["today"][0], runs["today"][1])
                    k = ("speed_loop_isr", "hall_isr", "uart_rx_byte", "link_poll_max_frame")
                    r = [c1[mode].worst[x] / c0[mode].worst[x] for x in k]
                    print(f"  {'ratio':<9} {b1.flash_bytes / b0.flash_bytes:>7.2f}  "
                          f"{(b1.ram_stack_bytes or 0) / (b0.ram_stack_bytes or 1):>15.2f}  {r[0]:>15.2f}  "
                          f"{r[1]:>6.2f}  {r[2]:>6.2f}  {r[3]:>7.2f}")
                print()
            for label, (b, c) in runs.items():
                summary.append((stem, "hall" if hall_speed else "encoder",
                                "IC1..IC3" if label == "today-ic" else "INT0..INT2", label, b, c))
                haz = []
                if target.unsaved_table_pointer(b):
                    haz.append("table pointer unsaved in " + ", ".join(target.unsaved_table_pointer(b)))
                sh = target.shared_static_helpers(b)
                if sh:
                    haz.append("static-operand helpers shared by an interrupt and main: " + ", ".join(sorted(sh)))
                print(f"  {label}: return stack {b.hw_stack_levels} levels; hazards: {'; '.join(haz) or 'none found'}")
                for n in b.notes:
                    print(f"    note: {n}")
            print()
    # the builds side by side: worst over the telemetry modes, each interrupt against its budget
    print("every build, worst over the telemetry modes (budgets: hall <= "
          f"{B.hall_isr_cycles}, UART RX <= {B.uart_rx_cycles}, speed loop <= {B.speed_loop_cycles:,} cycles)")
    print(f"  {'design':<32} {'speed':<8} {'halls on':<11} {'build':<9} {'flash B':>8} {'speed loop':>10} "
          f"{'hall':>5} {'UART rx':>7}  fits")
    for stem, speed, halls, label, b, c in summary:
        w = {k: max(c[m].worst[k] for m in c) for k in ("speed_loop_isr", "hall_isr", "uart_rx_byte")}
        fits = "yes" if not target.over_budget(b, w) else "NO: " + "; ".join(target.over_budget(b, w))
        print(f"  {stem:<32} {speed:<8} {halls:<11} {label:<9} {b.flash_bytes:>8,} {w['speed_loop_isr']:>10,} "
              f"{w['hall_isr']:>5} {w['uart_rx_byte']:>7}  {fits}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
