"""Does scheduling pay?  Scheduled fuzzy-hinf law against the best single-rule law of the same method.

For a profile (default examples/duy2008.toml): fuzzy-hinf six-step designs (Theorem 1, the same
certificate machinery and disk search) on

* ``dc-2``: the DC equivalent with the profile's rules (today's default: the rules coincide),
* ``avg-2``: the speed-dependent averaged model (picdrive.models.averaged), 2 rules at the premise
  ends (distinct gains),
* ``avg-2@lo-hi``: the same with the premise (rule centres) at 10 % and 95 % of the step target,
* ``avg-1@c``: the averaged model, one rule linearised at c rpm (c = 10, 50, 95 % of the step target),

then each verified law in the verification's plant (the twin's three-phase winding, the firmware's
speed measurement and current window: picdrive.analysis.steptest.run_sim with
picdrive.gate.BuiltDrive): a step from rest to 10 %, 50 % and 95 % of the step target, and at
each level the profile's load-torque step.  Prints settling (2 % band, sector-mean speed),
overshoot, load dip and load recovery per level and the worst case per law.

    PYTHONPATH=$PWD/host:$PWD/hil python3 bench/scheduling.py [profile.toml]
"""
from __future__ import annotations

import math
import sys
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
    out = [("dc-2", profile, {}), ("avg-2", profile, {"plant_model": "averaged"}),
           (f"avg-2@{lo:.0f}-{hi:.0f}", profile.replace(design={"premise_rpm": [lo, hi]}), {"plant_model": "averaged"})]
    for f in LEVELS:
        c = f * top
        d = min(c - n1, n2 - c)
        out.append((f"avg-1@{c:.0f}", profile.replace(design={"premise_rpm": [c - d, c + d]}),
                    {"plant_model": "averaged", "rules": 1}))
    return out


def level_figures(profile, law, drive, rpm: float) -> dict:
    from picdrive.analysis.steptest import run_sim, sim_plan, step_figures
    base = sim_plan(profile)
    plan = {**base, "target_rpm": rpm, "profile_target_rpm": rpm}
    sim = run_sim(profile, law, plan, measurement=drive.speed_measurement(profile, law), disturbances=False,
                  three_phase=drive.three_phase_plant)
    return step_figures(sim, plan, profile)


def main(argv):
    from picdrive.design.fuzzy_hinf import design
    from picdrive.gate import BuiltDrive
    from picdrive.profile import load_profile
    warnings.simplefilter("ignore")
    p = load_profile(argv[0] if argv else str(ROOT / "examples/duy2008.toml"))
    drive = BuiltDrive()
    top = p.speed_step_rpm()
    print(f"{p.name}: step target {top:.0f} rpm, load {p.control.load_torque_n_m:g} N m, premise {p.design['premise_rpm']} rpm")
    print(f"{'law':>12} {'status':>9} {'disk':>6} {'rules kp/ki/kc':>40} | " +
          " | ".join(f"{f * top:5.0f} rpm: settle ms  ovs %  dip rpm  rec ms" for f in LEVELS) +
          " | worst: settle ms  ovs %  dip % of level")
    for name, prof, opts in candidates(p):
        t0 = time.perf_counter()
        r = design(prof, drive=drive, progress=False, **opts)
        if r.law is None or not r.ok:
            print(f"{name:>12} {r.status:>9}  {'; '.join(x[:100] for x in r.reasons[:1])}")
            continue
        gains = " ".join(f"{g.kp:.3g}/{g.ki:.4g}/{g.kc:.3g}" for g in r.law.rules)
        cells, worst = [], [0.0, 0.0, 0.0]
        for f in LEVELS:
            g = level_figures(p, r.law, drive, f * top)
            cells.append(f"{1e3 * g['settling_s']:14.1f} {g['overshoot_pct']:6.2f} {g['load_dip_rpm']:8.2f} "
                         f"{1e3 * g['load_recovery_s']:6.1f}")
            worst = [max(worst[0], g["settling_s"]), max(worst[1], g["overshoot_pct"]),
                     max(worst[2], 100 * g["load_dip_rpm"] / (f * top))]
        print(f"{name:>12} {r.status:>9} {r.certificate.get('pole_disk_rad_s', math.nan):6.0f} {gains:>40} | "
              + " | ".join(cells) + f" | {1e3 * worst[0]:15.1f} {worst[1]:6.2f} {worst[2]:8.2f}"
              f"   ({time.perf_counter() - t0:.0f} s)", flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
