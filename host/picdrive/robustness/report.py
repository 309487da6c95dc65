"""What a tolerance study leaves for a person to read: report.md, its plots, the worst drives.

* :func:`summarise` -- the yield and its 95 % Wilson interval, the failures by
  limit, the parameters that drive failures (:func:`picdrive.robustness.stats.failure_drivers`),
  the worst drives, the speed of the run;
* :func:`write_report` -- ``plots/histograms.png`` (each metric's histogram
  with its limit), ``plots/drivers.png`` (each parameter's rank correlation
  with failing, and the strongest one's deviation against the worst
  figure-to-limit ratio), ``worst/<profile>.worst-<k>.toml`` (the worst drives
  as profiles: the nominal profile plus ``[as_built] seed``, which the twin
  draws the same drive from) and ``report.md``.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from ..tolerances import PARAMETERS, describe, draw, tolerances_toml
from .sample import METRICS, limits_of
from .stats import failure_drivers, wilson_interval

__all__ = ["summarise", "write_report", "worst_profile_text"]


def _col(name: str) -> str:
    return f"dev_{name}_{'deg' if PARAMETERS[name]['unit'] == 'deg' else 'pct'}"


def _float(v) -> float:
    try:
        return float(v)
    except (TypeError, ValueError):
        return math.nan


def summarise(study, rows: list[dict], *, wall_s: float, n_run: int, n_workers: int) -> dict:
    """The study's figures (see the module docstring)."""
    n = len(rows)
    status = [r["status"] for r in rows]
    passed = status.count("pass")
    failed = np.array([s != "pass" for s in status], bool)
    ratio = np.array([_float(r["worst_ratio"]) for r in rows])
    by_limit: dict[str, int] = {}
    for r in rows:
        for k in (r["failed_limits"] or "").split():
            by_limit[k] = by_limit.get(k, 0) + 1
    devs = {name: np.array([_float(r[_col(name)]) for r in rows]) for name in PARAMETERS}
    drivers = failure_drivers(devs, failed, ratio) if n >= 3 else []
    driver = next((d for d in drivers if math.isfinite(d["rho_fail"]) and d["p_fail"] < 0.05), None)
    order = sorted(range(n), key=lambda i: (-ratio[i] if math.isfinite(ratio[i]) else -math.inf, i))
    return {"n": n, "passed": passed, "yield": passed / n if n else math.nan, "yield_ci": wilson_interval(passed, n),
            "status_counts": {s: status.count(s) for s in ("pass", "fail", "error")},
            "failed_by_limit": dict(sorted(by_limit.items(), key=lambda kv: -kv[1])), "drivers": drivers,
            "driver": driver, "worst": [rows[i] for i in order[:max(0, int(getattr(study, 'worst', 3)))]],
            "wall_s": wall_s, "n_run": n_run, "n_workers": n_workers,
            "samples_per_s": n_run / wall_s if wall_s > 0 and n_run else math.nan,
            "samples_per_s_per_worker": n_run / wall_s / max(1, n_workers) if wall_s > 0 and n_run else math.nan}


def worst_profile_text(study, row: dict, rank: int) -> str:
    """A worst drive as a profile: the nominal profile's text, its tolerances (declared, so a later
    picdrive with other defaults draws the same drive) and ``[as_built]`` with the drive's seed."""
    prof = study.profile
    base = prof.path.read_text(encoding="utf-8") if prof.path is not None else ""
    dev = draw(prof.tolerances, int(row["seed"]))
    firmware = f"--hex {study.hex_name} --firmware <its firmware folder>" if study.processor else \
        "--firmware <the design's firmware folder>"
    head = [
        "",
        f"# --- drive {rank} of the tolerance study in {study.out} (picdrive robustness): sample {row['sample']}, "
        f"seed {row['seed']}",
        f"# deviations from the nominal profile: {dev.text()}",
        f"# its run: {row['status']}" + (f": {row['reason']}" if row["reason"] else ""),
        f"# the twin runs this drive: picdrive twin --profile <this file> {firmware}",
        f"#   (load step {study.plan['load_n_m'] * dev.load_factor:.6g} N m = the profile's x {dev.load_factor:.6g};"
        " the sections below are outside the profile hash: the nominal firmware matches)",
    ]
    text = base.rstrip("\n") + "\n" + "\n".join(head) + "\n"
    if "tolerances" not in prof.raw:
        text += "\n" + tolerances_toml(prof.tolerances)
    text += (f"\n[as_built]\nseed = {int(row['seed'])}\nstudy_seed = {int(study.seed)}\n"
             f"sample = {int(row['sample'])}\n")
    return text


def _plots(study, rows: list[dict], summary: dict, plots: Path) -> list[str]:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    plots.mkdir(parents=True, exist_ok=True)
    lims = limits_of(study.profile, study.plan)
    ok = np.array([r["status"] == "pass" for r in rows])
    fig, axes = plt.subplots(2, 3, figsize=(12, 6.5))
    fig.subplots_adjust(left=0.06, right=0.98, bottom=0.09, top=0.92, wspace=0.28, hspace=0.38)
    for ax, (key, (label, unit)) in zip(axes.ravel(), METRICS.items()):
        v = np.array([_float(r[key]) for r in rows])
        fin = np.isfinite(v)
        lim = lims[key]
        edges = np.histogram_bin_edges(np.concatenate([v[fin], [lim]]) if fin.any() else [0, lim], bins=30)
        h_ok, _ = np.histogram(v[fin & ok], edges)
        h_bad, _ = np.histogram(v[fin & ~ok], edges)
        ax.stairs(h_ok, edges, fill=True, color="tab:blue", label="pass")
        ax.stairs(h_ok + h_bad, edges, baseline=h_ok, fill=True, color="tab:red", label="fail")
        ax.axvline(lim, color="k", ls="--", lw=1.2, label=f"limit {lim:.4g} {unit}")
        if key == "final_error_rpm":
            ax.axvline(-lim, color="k", ls="--", lw=1.2)
        if (~fin).any():
            ax.text(0.98, 0.95, f"{int(np.count_nonzero(~fin))} never (inf) or not run", transform=ax.transAxes,
                    ha="right", va="top", fontsize=7, color="tab:red")
        ax.set_xlabel(f"{label}, {unit}")
        ax.set_ylabel("samples")
        ax.legend(fontsize=7, loc="upper center")
    fig.suptitle(f"{study.profile.name}: {summary['n']} drives, yield {100 * summary['yield']:.1f} %")
    fig.savefig(plots / "histograms.png", dpi=80)
    plt.close(fig)
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(12, 4.5))
    fig.subplots_adjust(left=0.11, right=0.98, bottom=0.12, top=0.95, wspace=0.25)
    dr = summary["drivers"]
    names = [d["parameter"] for d in dr]
    a1.barh(names, [d["rho_fail"] if math.isfinite(d["rho_fail"]) else 0.0 for d in dr], color="tab:red",
            label="with failing")
    a1.barh(names, [d["rho_margin"] if math.isfinite(d["rho_margin"]) else 0.0 for d in dr], color="none",
            edgecolor="k", label="with the worst figure / limit")
    a1.axvline(0, color="k", lw=0.8)
    a1.invert_yaxis()
    a1.set_xlabel("Spearman rank correlation")
    a1.legend(fontsize=8)
    top = (summary["driver"] or (dr[0] if dr else None))
    if top is not None:
        x = np.array([_float(r[_col(top["parameter"])]) for r in rows])
        y = np.array([_float(r["worst_ratio"]) for r in rows])
        never = ~np.isfinite(y)
        top_y = 1.2 * max(1.25, float(np.max(y[~never])) if (~never).any() else 1.0)
        y = np.where(never, top_y, y)
        a2.scatter(x[ok], y[ok], s=10, color="tab:blue", label="pass")
        a2.scatter(x[~ok & ~never], y[~ok & ~never], s=14, color="tab:red", label="fail")
        if never.any():
            a2.scatter(x[never], y[never], s=22, marker="x", color="tab:red",
                       label="never back in the band, or no run (drawn at the top)")
        a2.axhline(1.0, color="k", ls="--", lw=1.0, label="limit")
        u = "deg (electrical)" if PARAMETERS[top["parameter"]]["unit"] == "deg" else "%"
        a2.set_xlabel(f"{top['parameter']} deviation, {u}")
        a2.set_ylabel("worst figure / its limit")
        a2.legend(fontsize=8)
    fig.savefig(plots / "drivers.png", dpi=80)
    plt.close(fig)
    return ["plots/histograms.png", "plots/drivers.png"]


def write_report(study, rows: list[dict], summary: dict) -> None:
    """Write ``plots/``, ``worst/`` and ``report.md`` into the study folder (each file atomically)."""
    from .. import outputs
    out = study.out
    if rows:
        _plots(study, rows, summary, out / "plots")
    worst_files = []
    wdir = out / "worst"
    for k, row in enumerate(summary["worst"], 1):
        p = wdir / f"{study.profile.name}.worst-{k}.toml"
        wdir.mkdir(parents=True, exist_ok=True)
        outputs.write_text(p, worst_profile_text(study, row, k), what="worst drive profile")
        worst_files.append((p, row))
    lo, hi = summary["yield_ci"]
    lims = limits_of(study.profile, study.plan)
    twin = (f"the processor twin (the HEX `{study.hex_name}` on the PIC18 simulator)" if study.processor
            else "the software twin (the firmware's C compiled for this machine)")
    L = [f"# Tolerance study: {study.profile.name}, {study.design_path.name}", "",
         f"{summary['n']} drives drawn from the profile's tolerances (study seed {study.seed}), each running the "
         f"design's verification scenario on {twin}: a step from rest to {study.plan['target_rpm']:.0f} rpm, then "
         f"the load-torque step of {study.plan['load_n_m']:g} N m (x the drive's load factor) at "
         f"{study.plan['t_load_s']:g} s, to {study.plan['t_end_s']:g} s; judged by the verification's limits.", "",
         f"**Yield: {summary['passed']} / {summary['n']} = {100 * summary['yield']:.1f} %** "
         f"(95 % confidence interval {100 * lo:.1f} .. {100 * hi:.1f} %, Wilson score).", "",
         "| status | samples |", "|---|---|"]
    L += [f"| {k} | {v} |" for k, v in summary["status_counts"].items()]
    L += ["", "## Limits", "", "| figure | limit | samples failing it |", "|---|---|---|"]
    for key, (label, unit) in METRICS.items():
        L.append(f"| {label} | {'+-' if key == 'final_error_rpm' else '<'}{lims[key]:.4g} {unit} | "
                 f"{summary['failed_by_limit'].get(key, 0)} |")
    for key in ("fault", "simulation"):
        if summary["failed_by_limit"].get(key):
            L.append(f"| {'a fault latched' if key == 'fault' else 'the simulation failed'} | none | "
                     f"{summary['failed_by_limit'][key]} |")
    L += ["", "![histograms of each figure with its limit](plots/histograms.png)", "",
          "## Tolerances", "", "```"] + describe(study.profile.tolerances) + ["```", "",
                                                                            "## What drives the failures", ""]
    d = summary["driver"]
    if d is not None:
        L.append(f"**{d['parameter']}** ({PARAMETERS[d['parameter']]['what']}): Spearman rank correlation with "
                 f"failing {d['rho_fail']:+.2f} (p = {d['p_fail']:.2g}); "
                 + ("higher values fail more." if d["rho_fail"] > 0 else "lower values fail more."))
    elif summary["status_counts"].get("pass") == summary["n"]:
        L.append("No drive failed: no parameter drives failures in this study (the rank correlations with the "
                 "worst figure-to-limit ratio below show which parameters take margin).")
    else:
        L.append("No parameter's rank correlation with failing is significant at 5 %.")
    L += ["", "| parameter | rho with failing | p | rho with worst ratio |", "|---|---|---|---|"]
    for x in summary["drivers"]:
        f = (lambda v, s: "—" if not math.isfinite(v) else format(v, s))
        L.append(f"| {x['parameter']} | {f(x['rho_fail'], '+.3f')} | {f(x['p_fail'], '.2g')} | "
                 f"{f(x['rho_margin'], '+.3f')} |")
    L += ["", "![rank correlations and the strongest parameter](plots/drivers.png)", "",
          "## Worst drives", "",
          "Each is written as a profile in `worst/`: the nominal profile plus `[as_built] seed`, from which the "
          "twin draws the same deviations; `picdrive twin --profile worst/<file>` runs that drive with the "
          "nominal firmware.", "",
          "| file | sample | seed | status | worst figure / limit | reason |", "|---|---|---|---|---|---|"]
    for p, row in worst_files:
        L.append(f"| `worst/{p.name}` | {row['sample']} | {row['seed']} | {row['status']} | {row['worst_ratio']} | "
                 f"{row['reason'] or '—'} |")
    if summary["n_run"]:
        L += ["", "## Run", "",
              f"{summary['n_run']} samples in {summary['wall_s']:.1f} s on {summary['n_workers']} Dask worker(s): "
              f"{summary['samples_per_s']:.2f} samples/s, {summary['samples_per_s_per_worker']:.2f} per worker."]
    outputs.write_text(out / "report.md", "\n".join(L) + "\n", what="study report")
