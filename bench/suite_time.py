#!/usr/bin/env python3
"""The suite's cost in time, this tree beside an older commit (default 8cee402, the last one
before the subpackages), on this machine; the target: as fast or faster.

Prints, for each tree, the CPU seconds (user + sys, children included) and wall seconds of

* ``python3 -m picdrive --help`` (imports every command module: the CLI's start-up),
* ``pytest --collect-only`` of the whole suite (imports every test module and what it imports),
* a subset of test files present in both trees (import-heavy: the CLI's bad-input and output
  rules run picdrive in subprocesses; the protocol, codec, profile and model tests),

alternating the trees ``--repeat`` times and printing the median.  CPU time is the figure to
read on a shared machine; wall time moves with the other processes' load.

Usage: python3 bench/suite_time.py [--rev 8cee402] [--repeat 3]
"""
from __future__ import annotations

import argparse
import os
import re
import resource
import statistics
import subprocess
import sys
import tarfile
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SUBSET = ("test_profile.py", "test_protocol.py", "test_codec.py", "test_pcpwm.py", "test_pinmap.py",
          "test_p18f4431.py", "test_tfmodel.py", "test_dqmodel.py", "test_outputs.py", "test_bad_inputs.py")


def export(rev: str, dest: Path) -> Path:
    """The commit's tree, extracted (git archive) into ``dest``."""
    data = subprocess.run(["git", "-C", str(ROOT), "archive", rev], check=True, capture_output=True).stdout
    dest.mkdir(parents=True)
    with tempfile.TemporaryFile() as f:
        f.write(data)
        f.seek(0)
        with tarfile.open(fileobj=f) as t:
            t.extractall(dest, filter="data")
    return dest


def timed(tree: Path, cmd: list[str]) -> tuple[float, float, str]:
    """(CPU s of the child, wall s, last output line) of ``cmd`` run in ``tree`` on its own code."""
    env = dict(os.environ, PYTHONPATH=f"{tree / 'host'}:{tree / 'hil'}", MPLBACKEND="Agg")
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    r = subprocess.run(cmd, cwd=tree, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    lines = [ln for ln in (r.stdout + r.stderr).splitlines() if ln.strip()]
    return cpu, wall, lines[-1] if lines else f"exit {r.returncode}"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rev", default="8cee402", help="the older commit (default: before the restructure)")
    ap.add_argument("--repeat", type=int, default=3)
    a = ap.parse_args()
    py = sys.executable
    with tempfile.TemporaryDirectory(prefix="picdrive-suite-time-") as tmp:
        trees = {a.rev: export(a.rev, Path(tmp) / "old"), "this tree": ROOT}
        subset = [f"tests/{n}" for n in SUBSET if all((t / "tests" / n).exists() for t in trees.values())]
        cases = {
            "CLI start-up (--help)": [py, "-m", "picdrive", "--help"],
            "collect the suite": [py, "-m", "pytest", "--collect-only", "-q", "-p", "no:cacheprovider"],
            f"{len(subset)} test files in both": [py, "-m", "pytest", "-q", "-p", "no:cacheprovider", *subset],
        }
        print(f"suite time: {a.rev} beside this tree, median of {a.repeat} alternating runs "
              f"(load average now {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs)")
        for label, cmd in cases.items():
            res: dict[str, list] = {k: [] for k in trees}
            for _ in range(a.repeat):
                for name, tree in trees.items():
                    res[name].append(timed(tree, cmd))
            for name in trees:
                cpu = statistics.median(r[0] for r in res[name])
                wall = statistics.median(r[1] for r in res[name])
                last = re.sub(r" in [0-9.]+s.*", "", res[name][-1][2])[:60]
                print(f"  {label:28s} {name:10s} CPU {cpu:7.2f} s  wall {wall:7.2f} s   ({last})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
