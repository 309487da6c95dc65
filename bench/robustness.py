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

Wall clock and CPU time, both.  The CPU time of every process of the study
over its samples (the client with the in-process scheduler, each worker,
each worker's nanny; from /proc through psutil) gives the rate the same
cluster reaches on cores of its own: a worker runs its samples at the rate
its CPU per sample allows, and all the processes together get no more than
the machine's cores (``projected`` below).  The machine's load average is
printed before and after each row: on a shared machine the wall-clock
figures drop with it (two workers on two busy cores do not run twice as
fast), the CPU figures much less.

Usage: python3 bench/robustness.py [--samples N] [--twins software,processor] [--workers 1,2]
"""
from __future__ import annotations

import argparse
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


def _cpu_s(proc) -> float:
    """User + system CPU seconds of a process (0 once it is gone)."""
    try:
        t = proc.cpu_times()
        return t.user + t.system
    except Exception:                    # noqa: BLE001 -- the process ended
        return 0.0


def measure(processor: bool, workers: int, samples: int, tmp: Path) -> dict:
    import psutil

    from picdrive.robustness import study as st
    from picdrive.robustness.engine import open_client
    # the local cluster 'picdrive robustness' starts (its Dask settings)
    client, cluster = open_client(None, workers)
    try:
        quiet = lambda msg: None          # noqa: E731
        kind = "processor" if processor else "software"
        st.run_study(study(tmp / f"warm-{kind}-{workers}", 4 * workers, processor, 99),
                     scheduler=cluster.scheduler_address, workers=None, progress=False, log=quiet)
        worker_pids = set(client.run(os.getpid).values())
        me = psutil.Process()
        kids = me.children(recursive=True)
        got = {}
        inner = st._run_tasks

        def timed(*a, **k):
            # the CPU of the samples alone: the client's task loop, not the study's set-up or its report
            before = {p.pid: _cpu_s(p) for p in kids}
            c0, w0 = time.process_time(), time.perf_counter()
            try:
                return inner(*a, **k)
            finally:
                got["client_cpu_s"] = time.process_time() - c0
                got["loop_wall_s"] = time.perf_counter() - w0
                d = {p.pid: _cpu_s(p) - before[p.pid] for p in kids}
                got["worker_proc_cpu_s"] = [v for pid, v in d.items() if pid in worker_pids]
                got["nanny_cpu_s"] = sum(v for pid, v in d.items() if pid not in worker_pids)

        st._run_tasks = timed
        try:
            s = study(tmp / f"{kind}-{workers}", samples, processor, 1)
            la0 = os.getloadavg()[0]
            r = st.run_study(s, scheduler=cluster.scheduler_address, workers=None, progress=True, log=quiet)
            r["load"] = (la0, os.getloadavg()[0])
        finally:
            st._run_tasks = inner
        r.update(got)
        r["sim_s"] = s.plan["t_end_s"] + (0.045 if processor else 0.025)   # the scenario and the twin's set-up
        cpu = [float(x["cpu_s"]) for x in st.read_samples(s.out / "samples.csv") if x["cpu_s"]]
        r["worker_cpu_s"] = sum(cpu) / len(cpu)
        n = r["n_run"]
        total = r["client_cpu_s"] + r["nanny_cpu_s"] + sum(r["worker_proc_cpu_s"])
        r["total_cpu_per_sample_s"] = total / n
        # on cores of their own: the busiest worker's CPU, or all processes' CPU over the cores
        cores = os.cpu_count() or 1
        r["projected_per_s"] = n / max(max(r["worker_proc_cpu_s"]), total / cores)
        return r
    finally:
        client.close()
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
                n = r["n_run"]
                print(f"  {t:9s} twin, {w} worker(s), load average {r['load'][0]:.2f} -> {r['load'][1]:.2f}: "
                      f"{n} samples in {r['wall_s']:.1f} s, {r['samples_per_s']:.2f} samples/s, "
                      f"{r['samples_per_s_per_worker']:.2f} per worker "
                      f"({r['samples_per_s_per_worker'] * r['sim_s']:.1f} simulated s per wall s per worker)\n"
                      f"      CPU per sample: {1e3 * r['worker_cpu_s']:.1f} ms in the sample "
                      f"({r['sim_s'] / r['worker_cpu_s']:.0f} simulated s per CPU s), "
                      f"{1e3 * sum(r['worker_proc_cpu_s']) / n:.1f} ms its worker process, "
                      f"{1e3 * r['client_cpu_s'] / n:.1f} ms the client and scheduler, "
                      f"{1e3 * r['nanny_cpu_s'] / n:.1f} ms the nannies: "
                      f"{1e3 * r['total_cpu_per_sample_s']:.1f} ms in all; "
                      f"on {os.cpu_count()} cores of their own (projected from that CPU): "
                      f"{r['projected_per_s']:.2f} samples/s; yield {100 * r['yield']:.1f} %", flush=True)
    print()
    head = f"{'twin':10s}" + "".join(f" | {w} worker(s): samples/s wall (projected)" for w in workers)
    if len(workers) >= 2:
        head += f" | speedup {workers[0]} -> {workers[-1]}: wall (projected)"
    print(head)
    for t in twins:
        line = f"{t:10s}" + "".join(f" | {res[(t, w)]['samples_per_s']:8.2f} ({res[(t, w)]['projected_per_s']:6.2f})"
                                    + " " * 17 for w in workers)
        if len(workers) >= 2:
            r0, r1 = res[(t, workers[0])], res[(t, workers[-1])]
            line += (f" | {r1['samples_per_s'] / r0['samples_per_s']:.2f} x "
                     f"({r1['projected_per_s'] / r0['projected_per_s']:.2f} x)")
        print(line)
    if "processor" in twins:
        w = max(workers)
        r = res[("processor", w)]
        rate = r["samples_per_s"]
        print(f"\n10,000 processor-twin samples on {w} worker(s): "
              + (f"{r['wall_s'] / 60:.1f} min measured" if a.samples >= 10000 else
                 f"{10000 / rate / 60:.1f} min extrapolated from {rate:.2f} samples/s") + " (target <= 10 min)")
        print(f"  on {os.cpu_count()} cores of their own (projected from the CPU of every process): "
              f"{10000 / r['projected_per_s'] / 60:.1f} min")
    print(f"load average after: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
