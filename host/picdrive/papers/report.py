"""``picdrive report``: the papers' claims beside what picdrive computes, and the three designs compared.

Writes ``report.md`` and PNG figures (matplotlib, Agg) into ``out/report/`` or ``-o DIR``, whole or not at
all (built in a temporary folder, then renamed into place), following the output rule of
:mod:`picdrive.outputs` (an existing folder is replaced only when it is a report picdrive wrote).
"""
from __future__ import annotations

import shutil
import warnings
from pathlib import Path

import numpy as np

from ..errors import PicdriveError

__all__ = ["write_report", "compare_designs", "register"]

METHODS = ("fuzzy-hinf", "mixed-pid", "zn")


def compare_designs(profile, outdir: Path, *, progress: bool = True) -> str:
    """Design with the three methods, simulate step + load step, one plot and one table per profile."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from ..analysis.metrics import step_metrics
    from ..analysis.steptest import run_sim, sim_plan
    from ..gate import run_design, speed_measurement, three_phase_plant
    plan = sim_plan(profile)
    rows, sims = [], {}
    it = METHODS
    if progress:
        from tqdm import tqdm
        it = tqdm(METHODS, desc=f"designs {profile.name}", leave=False)
    for m in it:
        try:
            r = run_design(profile, m, progress=False)
        except PicdriveError as e:
            rows.append(f"| {m} | not available: {e} | | | | | |")
            continue
        if r.law is None:
            rows.append(f"| {m} | no law ({r.status}) | | | | | |")
            continue
        s = run_sim(profile, r.law, plan, measurement=speed_measurement(profile, r.law), three_phase=three_phase_plant)
        sims[m] = s
        a = s.t < plan["t_load_s"]
        if not np.all(np.isfinite(s.omega)):
            rows.append(f"| {m} ({r.status}) | diverged | | | | | |")
            continue
        mt = step_metrics(s.t[a], s.rpm[a], plan["target_rpm"], y0=0.0)
        err = plan["target_rpm"] - float(np.mean(s.rpm[-max(1, s.t.size // 10):]))
        rows.append(f"| {m} ({r.status}) | {mt.rise_time_s * 1e3:.1f} | {mt.settling_time_s * 1e3:.1f} | "
                    f"{mt.overshoot_pct:.2f} | {err:.3g} | {float(np.max(np.abs(s.u))):.2f} | "
                    f"{float(np.max(np.abs(s.i_bus))):.2f} |")
    fig, ax = plt.subplots(figsize=(7, 3.5))
    for m, s in sims.items():
        ax.plot(s.t, s.rpm, label=m)
    ax.axvline(plan["t_load_s"], color="k", lw=0.5)
    ax.set_xlabel("t [s]"); ax.set_ylabel("speed [rpm]")
    ax.set_title(f"{profile.name}: step to {plan['target_rpm']:.0f} rpm, load step {plan['load_n_m']:g} N m")
    ax.legend(fontsize=7); fig.tight_layout()
    png = f"compare_{profile.name}.png"
    fig.savefig(outdir / png, dpi=90); plt.close(fig)
    head = [f"### {profile.name}", "",
            f"Step from rest to {plan['target_rpm']:.0f} rpm, the 2016 load-torque disturbance w3, load step of "
            f"{plan['load_n_m']:g} N m at {plan['t_load_s']:g} s; the verification's six-step drive model "
            "(the motor's three-phase winding driven through the hall table, the bridge's conduction rule, the firmware's "
            "measurement and current window), sampled law.", "",
            "| design | rise [ms] | settling [ms] | overshoot [%] | steady error [rpm] | peak u [V] | peak i_line [A] |",
            "|---|---|---|---|---|---|---|"]
    return "\n".join(head + rows + ["", f"![{profile.name}]({png})", ""])


def write_report(outdir="out/report", *, profiles=("assawinchaichote2016", "duy2008"), quick: bool = False,
                 progress: bool = True) -> Path:
    """Build the whole report into ``outdir`` (replaced atomically)."""
    from .. import outputs
    from . import repro2008, repro2016
    from ..profile import load_profile
    outdir = outputs.dir_output(outdir, what="report folder")
    tmp = outputs.new_temp_dir(outdir, what="report folder")
    try:
        parts = ["# picdrive reproduction report", ""]
        parts.append(repro2016.section(tmp, quick=quick))
        parts.append(repro2008.section(tmp))
        parts.append("## The three designs compared\n")
        for name in profiles:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                prof = load_profile(name)
            parts.append(compare_designs(prof, tmp, progress=progress))
        (tmp / "report.md").write_text("\n".join(parts) + "\n", encoding="utf-8")
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    outputs.publish_dir(tmp, outdir, "report", what="report folder")
    return outdir / "report.md"


def _cmd(args) -> int:
    from ..outputs import dir_output
    dir_output(args.output, what="report folder")      # refused before the work, not after
    path = write_report(args.output, quick=args.quick, progress=not args.no_progress)
    print(f"wrote {path}")
    return 0


def register(sub) -> None:
    p = sub.add_parser("report", help="reproduction report: the papers' claims beside what picdrive computes",
                       description="Write report.md and PNG figures.")
    p.add_argument("-o", "--output", default="out/report", help="output folder (default out/report)")
    p.add_argument("--quick", action="store_true", help="shorter simulations")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=_cmd)
