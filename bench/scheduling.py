"""Does scheduling pay?  Scheduled fuzzy-hinf law against the best single-rule law of the same method.

For a profile (default examples/duy2008.toml): fuzzy-hinf six-step designs (Theorem 1, the same
certificate machinery and disk search) on

* ``dc-2``: the DC equivalent with the profile's rules (today's default: the rules coincide),
* ``avg-2``: the speed-dependent averaged model (picdrive.models.averaged), 2 rules at the premise
  ends (distinct gains),
* ``avg-2@lo-hi``: the same with the premise (rule centres) at 10 % and 95 % of the step target,
* ``avg-1@c``: the averaged model, one rule linearised at c rpm (c = 10, 50, 95 % of the step target),
  and the 50 % one again at ``avg-2``'s pole disk (``dNNN``: the same bandwidth target),

then each verified law in the motor twin with the firmware generated from the design in the loop
(picdrive.gate.twin_run, row "twin") and in the verification's simulation (the twin's three-phase
winding, the firmware's speed measurement and current window: picdrive.analysis.steptest.run_sim
with picdrive.gate.BuiltDrive, row "model"): a step from rest to 10 %, 50 % and 95 % of the step
target, and at each level the profile's load-torque step.  Prints settling (2 % band, sector-mean speed),
overshoot, load dip and load recovery per level and the worst case per law.

    PYTHONPATH=$PWD/host:$PWD/hil python3 bench/scheduling.py [profile.toml]
"""
from __future__ import annotations

import math
import sys
import tempfile
import time
import warnings
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
LEVELS = (0.10, 0.50, 0.95)


def candidates(profile):
    """(name, profile to design on, fuzzy-hinf options)."""
    top = profile.speed_step_rpm()
    n1, n2 = profile.design["premise_rpm"]
    lo, hi = LEVELS[0] * top, LEVELS[-1] * top
    out = [("dc-2", profile, {"plant_model": "six-step"}), ("avg-2", profile, {"plant_model": "averaged"}),
           (f"avg-2@{lo:.0f}-{hi:.0f}", profile.replace(design={"premise_rpm": [lo, hi]}), {"plant_model": "averaged"})]
    for f in LEVELS:
        c = f * top
        d = min(c - n1, n2 - c)
        out.append((f"avg-1@{c:.0f}", profile.replace(design={"premise_rpm": [c - d, c + d]}),
                    {"plant_model": "averaged", "rules": 1}))
    return out


def level_figures(profile, result, drive, rpm: float, design_path) -> tuple[dict, dict]:
    """(twin, model) figures of the step from rest to ``rpm`` and the load step there: the motor twin
    with the firmware generated from the design in the loop (picdrive.gate.twin_run), and the
    verification's simulation (three-phase plant, the firmware's measurement)."""
    from picdrive.analysis.steptest import run_sim, sim_plan, step_figures
    from picdrive.gate import twin_run
    base = sim_plan(profile)
    plan = {**base, "target_rpm": rpm, "profile_target_rpm": rpm}
    tw = step_figures(twin_run(profile, design_path, plan), plan, profile)
    sim = run_sim(profile, result.law, plan, measurement=drive.speed_measurement(profile, result.law),
                  disturbances=False, three_phase=drive.three_phase_plant)
    return tw, step_figures(sim, plan, profile)


def main(argv):
    from picdrive.design.fuzzy_hinf import design
    from picdrive.gate import BuiltDrive
    from picdrive.profile import load_profile
    from picdrive.result import save_design
    warnings.simplefilter("ignore")
    p = load_profile(argv[0] if argv else str(ROOT / "examples/duy2008.toml"))
    drive = BuiltDrive()
    top = p.speed_step_rpm()
    print(f"{p.name}: step target {top:.0f} rpm, load {p.control.load_torque_n_m:g} N m, premise {p.design['premise_rpm']} rpm")
    print(f"{'law':>12} {'status':>9} {'disk':>6} {'rules kp/ki/kc':>40} {'run':>5} | " +
          " | ".join(f"{f * top:5.0f} rpm: settle ms  ovs %  dip rpm  rec ms" for f in LEVELS) +
          " | worst: settle ms  ovs %  dip % of level")
    rows = candidates(p)
    k = 0
    while k < len(rows):
        name, prof, opts = rows[k]
        k += 1
        t0 = time.perf_counter()
        r = design(prof, drive=drive, progress=False, **opts)
        if r.law is None or not r.ok:
            print(f"{name:>12} {r.status:>9}  {'; '.join(x[:100] for x in r.reasons[:1])}")
            continue
        if name == "avg-2":        # the single mid rule at the scheduled law's disk too: same bandwidth target
            mid = next(r_ for r_ in rows if r_[0] == f"avg-1@{LEVELS[1] * top:.0f}")
            rows.append((f"{mid[0]} d{r.certificate['pole_disk_rad_s']:.0f}", mid[1],
                         {**mid[2], "pole_disk_rad_s": r.certificate["pole_disk_rad_s"]}))
        gains = " ".join(f"{g.kp:.3g}/{g.ki:.4g}/{g.kc:.3g}" for g in r.law.rules)
        with tempfile.TemporaryDirectory(prefix="picdrive-sched-") as tmp:
            path = Path(tmp) / f"{p.name}.fuzzy-hinf.design.json"
            save_design(r, path)
            figs = [level_figures(prof, r, drive, f * top, path) for f in LEVELS]
        for row, label in ((0, "twin"), (1, "model")):
            cells, worst = [], [0.0, 0.0, 0.0]
            for f, g2 in zip(LEVELS, figs):
                g = g2[row]
                cells.append(f"{1e3 * g['settling_s']:14.1f} {g['overshoot_pct']:6.2f} {g['load_dip_rpm']:8.2f} "
                             f"{1e3 * g['load_recovery_s']:6.1f}")
                worst = [max(worst[0], g["settling_s"]), max(worst[1], g["overshoot_pct"]),
                         max(worst[2], 100 * g["load_dip_rpm"] / (f * top))]
            head = (f"{name:>12} {r.status:>9} {r.certificate.get('pole_disk_rad_s', math.nan):6.0f} {gains:>40}"
                    if row == 0 else " " * 70)
            print(f"{head} {label:>5} | " + " | ".join(cells) + f" | {1e3 * worst[0]:15.1f} {worst[1]:6.2f} "
                  f"{worst[2]:8.2f}" + (f"   ({time.perf_counter() - t0:.0f} s)" if row else ""), flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
