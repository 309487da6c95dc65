#!/usr/bin/env python3
"""Throughput of ``picdrive robustness`` (printed; not a timed test).

For the software twin (the firmware's C) and the processor twin (the bundled
HEX on the PIC18 simulator), a tolerance study of duy2008's fuzzy-hinf design
with the verification's full scenario (step from rest to 2400 rpm, the load
step at 0.6 s, to 1.2 s) on a Dask LocalCluster of 1 and of 2 single-threaded
worker processes: samples per second, per worker, the simulated seconds per
wall second of each worker, and the speedup from 1 to 2 workers, side by side.
Each cluster runs a warm-up study first (the workers' imports and the twin's
first load), so the figures are the steady state; the time to 10,000 samples
is extrapolated from them (``--samples 10000`` runs it).

The machine's load average is printed before and after: on a shared machine
the figures drop with it (two workers on two busy cores do not run twice as
fast).

Usage: python3 bench/robustness.py [--samples N] [--twins software,processor] [--workers 1,2]
"""
from __future__ import annotations

import argparse
import logging
import os
import sys
import tempfile
import time
import warnings
from pathlib import Path
from types import SimpleNamespace

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

ROOT = Path(__file__).resolve().parents[1]
DESIGN = ROOT / "examples" / "duy2008.fuzzy-hinf.design.json"
HEX = ROOT / "firmware_build" / "duy2008" / "duy2008.hex"


def study(out: Path, samples: int, processor: bool, seed: int):
    from picdrive.robustness.study import prepare_study
    args = SimpleNamespace(profile="duy2008", design=str(DESIGN), hex=str(HEX) if processor else None,
                           samples=samples, seed=seed, output=str(out), phase_s=None)
    return prepare_study(args)


def measure(processor: bool, workers: int, samples: int, tmp: Path) -> dict:
    from distributed import LocalCluster

    from picdrive.robustness.study import run_study
    cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=None,
                           silence_logs=logging.ERROR)
    try:
        quiet = lambda msg: None          # noqa: E731
        kind = "processor" if processor else "software"
        run_study(study(tmp / f"warm-{kind}-{workers}", 4 * workers, processor, 99), scheduler=cluster.scheduler_address,
                  workers=None, progress=False, log=quiet)
        s = study(tmp / f"{kind}-{workers}", samples, processor, 1)
        c0 = time.process_time()
        r = run_study(s, scheduler=cluster.scheduler_address, workers=None, progress=True, log=quiet)
        r["client_cpu_s"] = time.process_time() - c0
        r["sim_s"] = s.plan["t_end_s"] + (0.045 if processor else 0.025)   # the scenario and the twin's set-up
        from picdrive.robustness.study import read_samples
        cpu = [float(x["cpu_s"]) for x in read_samples(s.out / "samples.csv") if x["cpu_s"]]
        r["worker_cpu_s"] = sum(cpu) / len(cpu)
        return r
    finally:
        cluster.close()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--samples", type=int, default=200, help="samples per measurement (default 200)")
    ap.add_argument("--twins", default="software,processor")
    ap.add_argument("--workers", default="1,2")
    a = ap.parse_args()
    warnings.simplefilter("ignore")
    twins = [t.strip() for t in a.twins.split(",") if t.strip()]
    workers = [int(w) for w in a.workers.split(",")]
    print(f"bench/robustness.py on {os.cpu_count()} CPUs, load average {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    print(f"duy2008 fuzzy-hinf, the verification's scenario, {a.samples} samples per row")
    res = {}
    with tempfile.TemporaryDirectory(prefix="bench-robustness-") as tmp:
        for t in twins:
            for w in workers:
                r = measure(t == "processor", w, a.samples, Path(tmp))
                res[(t, w)] = r
                print(f"  {t:9s} twin, {w} worker(s): {r['n_run']} samples in {r['wall_s']:.1f} s, "
                      f"{r['samples_per_s']:.2f} samples/s, {r['samples_per_s_per_worker']:.2f} per worker "
                      f"({r['samples_per_s_per_worker'] * r['sim_s']:.1f} simulated s per wall s per worker); "
                      f"a sample takes {1e3 * r['worker_cpu_s']:.0f} ms of its worker's CPU "
                      f"({r['sim_s'] / r['worker_cpu_s']:.0f} simulated s per CPU s) and "
                      f"{1e3 * r['client_cpu_s'] / max(1, r['n_run']):.1f} ms of the client's; "
                      f"yield {100 * r['yield']:.1f} %", flush=True)
    print()
    head = f"{'twin':10s}" + "".join(f" | {w} worker(s): samples/s (per worker)" for w in workers)
    if len(workers) >= 2:
        head += f" | speedup {workers[0]} -> {workers[-1]}"
    print(head)
    for t in twins:
        line = f"{t:10s}" + "".join(f" | {res[(t, w)]['samples_per_s']:8.2f} ({res[(t, w)]['samples_per_s_per_worker']:.2f})"
                                    + " " * 17 for w in workers)
        if len(workers) >= 2:
            line += f" | {res[(t, workers[-1])]['samples_per_s'] / res[(t, workers[0])]['samples_per_s']:.2f} x"
        print(line)
    if "processor" in twins:
        w = max(workers)
        rate = res[("processor", w)]["samples_per_s"]
        print(f"\n10,000 processor-twin samples on {w} worker(s): "
              + (f"{res[('processor', w)]['wall_s'] / 60:.1f} min measured" if a.samples >= 10000 else
                 f"{10000 / rate / 60:.1f} min extrapolated from {rate:.2f} samples/s") + " (target <= 10 min)")
        cpu = res[("processor", w)]["worker_cpu_s"] + res[("processor", w)]["client_cpu_s"] / res[("processor", w)]["n_run"]
        print(f"  on {w} cores of their own (each sample's worker CPU plus the client's share): "
              f"{10000 * cpu / w / 60:.1f} min")
    print(f"load average after: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
