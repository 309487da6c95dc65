#!/usr/bin/env python3
"""Speed of the PIC18 instruction-set simulator (hil/picdrive_hil/csrc/pic18cpu.c).

    python3 bench/pic18sim.py [--minsns 20]

Runs representative programs from the differential corpus (tests/support/pic18diff.py),
assembled by gpasm, in the simulator's normal (data-sheet) build with no breakpoints, run by cycles, and
prints simulated instructions and instruction cycles per CPU second (time.process_time of
the one pic18_run call, best of three runs):
  arith   what compiled code does: 16x16->32 MULWF products, 32-bit add/sub/negate/shift,
          a 16/8 division loop, xorshift operands (calls, returns, skips, branches, MOVFF)
  random  seeded random instruction mix (ALU, literals, bit ops, skips, branches, MOVFF,
          all FSR forms)
Goal: >= 200 M simulated instructions per CPU second.
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(ROOT / "hil"))
sys.path.insert(0, str(ROOT / "host"))

from picdrive.firmware import ihex  # noqa: E402
from picdrive_hil.pic18 import Pic18  # noqa: E402
from support import pic18diff as D  # noqa: E402


def cycles_per_insn(prog: D.Program, img) -> float:
    """The program's cycles per instruction over its first 10^5 instructions."""
    cpu = Pic18(img)
    cpu.run(insns=100_000)
    return cpu.cycles / cpu.insns


def measure(prog: D.Program, n_insns: int, wd: Path) -> tuple[float, float, int]:
    hexp, _ = D.assemble(prog, wd)
    img = ihex.load_hex(hexp)
    best = None
    for _ in range(3):    # best of three: the machine is shared, the least-disturbed run counts
        cpu = Pic18(img)
        cpu.run(insns=10_000)                   # warm caches, past the prologue
        i0, c0 = cpu.insns, cpu.cycles
        # by cycles, as the twin runs it (an instruction limit checks every instruction)
        n_cycles = int(n_insns * cycles_per_insn(prog, img))
        t0 = time.process_time()
        st = cpu.run(cycles=n_cycles)
        dt = time.process_time() - t0
        if st != "ok":
            raise SystemExit(f"{prog.name}: the core stopped ({cpu.stop.message}) -- not a speed figure")
        r = ((cpu.insns - i0) / dt, (cpu.cycles - c0) / dt, cpu.insns - i0)
        best = r if best is None or r[0] > best[0] else best
    return best


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--minsns", type=float, default=20, help="million instructions per program (default 20; the arithmetic program runs 22 M before its end loop)")
    a = ap.parse_args()
    n = int(a.minsns * 1e6)
    # enough loop passes that the program does not reach 'done' within n instructions
    progs = [D.prog_arith(iterations=65_000), D.prog_random(2, blocks=60, length=40, repeat=255)]
    with tempfile.TemporaryDirectory(prefix="pic18sim-") as td:
        print(f"PIC18 simulator speed ({a.minsns:g} M instructions per program, CPU time)")
        worst = None
        for p in progs:
            ips, cps, done = measure(p, n, Path(td))
            worst = ips if worst is None else min(worst, ips)
            print(f"  {p.name:10s} {ips / 1e6:8.1f} M instructions/s  {cps / 1e6:8.1f} M cycles/s  "
                  f"({done / 1e6:.0f} M instructions)")
        print(f"  slowest    {worst / 1e6:8.1f} M instructions/s (goal >= 200)")


if __name__ == "__main__":
    main()
