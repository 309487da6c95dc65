#!/usr/bin/env python3
"""Where the speed-loop interrupt's cycles go: cycles per function, measured on the PIC18 core in gpsim.

Builds picdrive.firmware.gpsim's timing harness around a generated firmware
folder (one telemetry mode), stops gpsim at each speed-loop call of the corpus
(the harness's ``_harness_speed_call`` label) and single-steps it, reading the
cycle counter and PC of every instruction.  Each instruction's cycles go to the
function whose code holds it (exclusive) and to every function on the call
stack (inclusive; CALL/RCALL push, RETURN/RETFIE/RETLW pop).  Prints, for the
worst call of the corpus (most cycles, interrupt entry not included), each
function's calls, exclusive and inclusive cycles, and the worst inclusive
cycles of each function over all calls.

Usage:
  python3 bench/isr_profile.py                          # firmware_build/duy2008, telemetry off
  python3 bench/isr_profile.py --design examples/duy2008.zn.design.json --mode 4+capture
  python3 bench/isr_profile.py --folder some/generated/folder
"""
from __future__ import annotations

import argparse
import re
import subprocess
import sys
import tempfile
from collections import defaultdict
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from picdrive.firmware import gpsim

HERE = Path(__file__).resolve().parent
STEPS_PER_CALL = 7000          # instructions stepped after each break: more than one speed-loop call
_LINE = re.compile(r"^0x([0-9A-Fa-f]{16}) \S+ 0x([0-9A-Fa-f]+) 0x[0-9A-Fa-f]+ (\S+)")


def trace(folder: Path, work: Path, mode: str, steps: int = STEPS_PER_CALL, jobs: int = 2):
    """Run the timing harness in gpsim, single-stepping every speed-loop call: (Build, [[(cycle, pc, op)]])."""
    b, keys, counts, script = gpsim.build_timing(folder, work, (mode,))
    calls = sum(n for k, n in counts.items() if k.split("|", 1)[-1].startswith("speed_loop_isr:"))
    at = b.functions.get("_harness_speed_call")
    label = at.address if at else _map_symbol(b.hex_path.with_suffix(".map"), "_harness_speed_call")
    base = [ln for ln in script.read_text().splitlines() if ln not in ("run", "dump r", "quit", "")]
    base.append(f"break e 0x{label:x}")

    def one(k):
        # one gpsim run per call (gpsim slows down on long scripts): run to the k-th break, then step
        prof = work / f"profile{k}.stc"
        prof.write_text("\n".join(base + ["run"] * (k + 1) + ["step"] * steps + ["quit", ""]))
        r = subprocess.run(["gpsim", "-i", "-S", "disable", "-p", gpsim.TIMING_PROCESSOR, "-c", str(prof),
                            str(b.hex_path.resolve())], capture_output=True, stdin=subprocess.DEVNULL, timeout=900)
        run = []
        for ln in (r.stdout + r.stderr).decode("latin-1").splitlines():
            m = _LINE.match(ln)
            if m:
                cyc, pc, op = int(m[1], 16), int(m[2], 16), m[3].lower()
                if pc == label and run and len(run) > 2:
                    break                  # the next speed-loop call
                if pc == label or run:
                    run.append((cyc, pc, op))
        return run

    with ThreadPoolExecutor(max_workers=jobs) as ex:
        runs = [r for r in ex.map(one, range(calls)) if r]
    return b, label, runs


def _map_symbol(map_path: Path, name: str) -> int:
    for ln in map_path.read_text().splitlines():
        parts = ln.split()
        if len(parts) >= 3 and parts[0] == name and parts[2] == "program":
            return int(parts[1], 16)
    raise SystemExit(f"{map_path} has no symbol {name}: is the timing harness up to date?")


def attribute(run, label: int, funcs: list[tuple[int, int, str]]):
    """One speed-loop call: ({function: exclusive}, {function: inclusive}, {function: calls}, total)."""
    def owner(pc):
        lo, hi = 0, len(funcs) - 1
        best = "?"
        while lo <= hi:
            mid = (lo + hi) // 2
            if funcs[mid][0] <= pc:
                best = funcs[mid][2] if pc < funcs[mid][0] + funcs[mid][1] else "?"
                lo = mid + 1
            else:
                hi = mid - 1
        return best

    starts = {a for a, _s, _n in funcs}
    excl: dict = defaultdict(int)
    incl: dict = defaultdict(int)
    ncall: dict = defaultdict(int)
    stack: list[str] = []
    total = 0
    ret = label + 4                    # the CALL's return address: the interrupt has returned
    for (cyc, pc, op), nxt in zip(run, run[1:]):
        if pc == ret:
            break
        c = nxt[0] - cyc
        if pc == label:                # the harness's CALL itself: the interrupt entry
            stack = [owner(nxt[1])]
            ncall[stack[0]] += 1
            total += c
            excl[stack[0]] += c
            incl[stack[0]] += c
            continue
        f = owner(pc)
        total += c
        excl[f] += c
        for g in set(stack):
            incl[g] += c
        if op in ("call", "rcall"):
            callee = owner(nxt[1])
            stack.append(callee)
            if nxt[1] in starts:           # not an RCALL to a local label inside a function
                ncall[callee] += 1
        elif op in ("return", "retfie", "retlw") and stack:
            stack.pop()
    return excl, incl, ncall, total


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--folder", type=Path, help="a generated firmware folder (default firmware_build/duy2008)")
    ap.add_argument("--design", type=Path, help="generate this design's firmware first (examples/*.design.json)")
    ap.add_argument("--mode", default="off", choices=gpsim.TELEMETRY_MODES)
    ap.add_argument("--top", type=int, default=40, help="functions to print")
    a = ap.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="isr_profile.") as t:
        work = Path(t)
        folder = a.folder or HERE.parent / "firmware_build" / "duy2008"
        if a.design:
            sys.path.insert(0, str(HERE))
            from target import generate_new   # bench/target.py: one way to generate a design's firmware
            folder, _ = generate_new(a.design, work / "fw")
        b, label, runs = trace(folder, work / "timing", a.mode)
        if not runs:
            print("gpsim stopped at no speed-loop call (see the timing build)", file=sys.stderr)
            return 1
        funcs = sorted((f.address, f.size, n) for n, f in b.functions.items())
        per = [attribute(r, label, funcs) for r in runs]
    worst_i = max(range(len(per)), key=lambda i: per[i][3])
    excl, incl, ncall, total = per[worst_i]
    worst_incl: dict = defaultdict(int)
    for e, i, n, t in per:
        for f, c in i.items():
            worst_incl[f] = max(worst_incl[f], c)
    print(f"{folder}  telemetry {a.mode}: {len(per)} speed-loop calls, worst {total} cycles "
          f"(call {worst_i + 1}; + {gpsim.ENTRY_CYCLES} interrupt entry = {total + gpsim.ENTRY_CYCLES}), "
          f"all: {', '.join(str(p[3]) for p in per)}")
    print(f"{'function':34s} {'calls':>5s} {'exclusive':>9s} {'inclusive':>9s} {'worst incl':>10s}  (worst call)")
    for f in sorted(incl, key=lambda k: (-incl[k], k))[:a.top]:
        print(f"{f:34s} {ncall.get(f, 0):5d} {excl.get(f, 0):9d} {incl[f]:9d} {worst_incl[f]:10d}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
