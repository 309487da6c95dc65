"""One drive of a tolerance study: the verification's scenario on it, its figures and its verdict.

:func:`run_sample` runs :func:`picdrive.gate.twin_scenario` (the design's
verification step and load step, on the software or the processor twin) on
the drive an ``[as_built]`` seed names, judges the run as the verification
judges it (:func:`picdrive.analysis.steptest.step_figures` against
:func:`picdrive.design.verify.run_limits`) and returns one flat row.  A
simulation that fails (the twin stops, the firmware never starts the bridge)
is a failed sample with its reason, never an exception.
"""
from __future__ import annotations

import dataclasses
import math
import time

from ..tolerances import PARAMETERS, draw

__all__ = ["METRICS", "STATUS", "row_fields", "run_sample", "judge"]

#: the figures of a run, as the verification names them (picdrive.design.verify.RUN_FIGURES), with the
#: stall check's dip: key -> (label, unit)
METRICS = {"settling_s": ("settling (2 % band)", "s"), "overshoot_pct": ("overshoot", "%"),
           "load_recovery_s": ("recovery after the load step", "s"), "final_error_rpm": ("final error", "rpm"),
           "peak_current_ripple_a": ("peak line current", "A"), "load_dip_rpm": ("speed dip at the load step", "rpm")}

#: a sample's status: it met every limit, it missed one or more, or its simulation failed
STATUS = ("pass", "fail", "error")


def row_fields() -> list[str]:
    """The CSV columns of a sample, in order."""
    return (["sample", "seed", "status", "failed_limits", "reason", "faults"]
            + [f"dev_{k}_{'deg' if v['unit'] == 'deg' else 'pct'}" for k, v in PARAMETERS.items()]
            + list(METRICS) + ["worst_ratio", "cpu_s", "worker"])


def limits_of(profile, plan) -> dict:
    """Each metric's limit (the verification's, :func:`picdrive.design.verify.run_limits`; the dip:
    below the target, the drive must not stall)."""
    from ..design.verify import run_limits
    return {**run_limits(profile, plan), "load_dip_rpm": plan["target_rpm"]}


def judge(figures: dict, limits: dict) -> tuple[list[str], list[str], float]:
    """The verdict of a run's figures: the failed limits (keys), their phrases, and the worst ratio
    of a figure to its limit (``|final error|``; > 1 is a failure, the largest over the metrics)."""
    from ..design.verify import failed_figures, run_failures
    phrases = run_failures(figures, limits, "this drive")
    keys = failed_figures(figures, limits)
    if not figures["load_dip_rpm"] < limits["load_dip_rpm"]:
        keys.append("load_dip_rpm")
        phrases.append(f"this drive: speed dip at the load step {figures['load_dip_rpm']:.5g} rpm (limit "
                       f"{limits['load_dip_rpm']:.5g} rpm: it stalled)")
    ratios = []
    for k in METRICS:
        v, lim = figures[k], limits[k]
        v = abs(v) if k == "final_error_rpm" else v
        ratios.append(math.inf if not math.isfinite(v) else (v / lim if lim > 0 else (0.0 if v <= 0 else math.inf)))
    return keys, phrases, max(ratios)


def run_sample(profile, firmware_dir, table, plan, index: int, seed: int, *, hex_file=None) -> dict:
    """Run drive ``seed`` (sample ``index``) and judge it; returns one row (:func:`row_fields`).

    Parameters
    ----------
    profile : picdrive.profile.Profile
        The nominal profile (its tolerances); the drive is ``profile`` with ``as_built_seed = seed``.
    firmware_dir : pathlib.Path or None
        The generated firmware folder (software twin), or the folder of the HEX's board.json.
    table : picdrive.link.protocol.Table
        The firmware's parameter table.
    plan : dict
        The verification's plan (:func:`picdrive.analysis.steptest.sim_plan`).
    index, seed : int
        The sample's number in the study and its seed (:func:`picdrive.tolerances.sample_seed`).
    hex_file : pathlib.Path, optional
        Run this HEX on the processor twin.
    """
    import os
    import socket

    from ..analysis.steptest import step_figures
    from ..gate import twin_scenario
    drive = dataclasses.replace(profile, as_built_seed=int(seed))
    dev = draw(profile.tolerances, int(seed))
    row = {"sample": int(index), "seed": int(seed), "faults": "", "failed_limits": "", "reason": "",
           "worker": f"{socket.gethostname()}:{os.getpid()}"}
    for k, v in dev.values().items():
        row[f"dev_{k}_{'deg' if PARAMETERS[k]['unit'] == 'deg' else 'pct'}"] = round(v, 6)
    t0 = time.process_time()
    try:
        run = twin_scenario(drive, firmware_dir, table, plan, hex_file=hex_file)
        fig = step_figures(run, plan, drive)
    except Exception as e:            # noqa: BLE001 -- a failed simulation is a failed sample, the study goes on
        row.update({k: "" for k in METRICS})
        row.update(status="error", reason=f"the simulation failed: {type(e).__name__}: {e}", worst_ratio="inf",
                   failed_limits="simulation")
        row["cpu_s"] = round(time.process_time() - t0, 4)
        return row
    lims = limits_of(drive, plan)
    keys, phrases, worst = judge(fig, lims)
    if run.faults:
        keys.append("fault")
        phrases.append("fault: " + "; ".join(run.faults))
    row.update({k: round(float(fig[k]), 6) if math.isfinite(fig[k]) else "inf" for k in METRICS})
    row.update(status="fail" if keys else "pass", failed_limits=" ".join(keys),
               reason="; ".join(p.removeprefix("this drive: ") for p in phrases), faults="; ".join(run.faults),
               worst_ratio=round(worst, 6) if math.isfinite(worst) else "inf")
    row["cpu_s"] = round(time.process_time() - t0, 4)
    return row
