#!/usr/bin/env python3
"""Why the averaged-model fuzzy-hinf design fails on motors picdrive has never seen.

For each profile (default: the two corpus windings whose DC-equivalent design verifies, BLY171D and the
Multistar 4225) and each pole disk of the design's search (``pi/(2 Ts) x 0.8^k``), the fuzzy-hinf
design (``picdrive.gate.run_design``, the disk given, no simulation) on the averaged model and on the DC
equivalent: the LMI outcome, gamma, the rule gains, and the sampled loop's spectral radius with the
firmware's measurement (:func:`picdrive.analysis.sampled.six_step_closed_loop`) on two plants at the
law's check points (R at its uncertainty):

* ``DC`` -- the DC equivalent, the plant of the verification's ``sampled_spectral_radius`` check;
* ``avg`` -- the averaged model linearised at each check speed (``AveragedModel.dc_form``), the plant
  the averaged rules were designed on.

Then the first averaged-model disk of the search whose loop fails on the DC plant but passes
(<= the search's 0.95) on the averaged plant runs the verification's step and load step in the
three-phase plant (:func:`picdrive.analysis.steptest.run_sim`, R x 0.9, 1, 1.1): what the plant the
twin runs does with gains the check rejects.  Nothing is written; docs/scheduling.md quotes the figures.

    python3 bench/averaged_sampled.py [NAME ...] [--disks K]
"""
from __future__ import annotations

import argparse
import math
import sys
import time
import warnings
from pathlib import Path
from types import SimpleNamespace

ROOT = Path(__file__).resolve().parents[1]
DEFAULT = ("anaheim_bly171d_24v_4000", "turnigy_multistar_4225_610kv")
RPM = 2 * math.pi / 60


def run(name: str, n_disks: int) -> None:
    from picdrive.analysis.sampled import sampled_radius
    from picdrive.analysis.steptest import run_sim, sim_plan, step_figures
    from picdrive.gate import BuiltDrive, run_design, speed_measurement, three_phase_plant
    from picdrive.models.averaged import identify_cached
    from picdrive.profile import load_profile
    path = Path(name) if name.endswith(".toml") else ROOT / "tests" / "motors" / f"{name}.toml"
    prof = load_profile(path)
    m, load = prof.motor, prof.control.load_torque_n_m
    eps = float(prof.design.get("resistance_uncertainty", 0.1))
    avg = identify_cached(prof, BuiltDrive().three_phase_plant)
    step = prof.speed_step_rpm()
    top_prem = prof.design.get("premise_rpm", [0.0, prof.control.speed_max_rpm])[-1]
    print(f"\n## {prof.name}: R = {m.r_line_ohm:.4g} ohm, L/R = {1e3 * m.l_line_h / m.r_line_ohm:.3g} ms, "
          f"step target {step:.0f} rpm, identified to {avg.w_range[1] / RPM:.0f} rpm, premise top {top_prem:.0f} rpm")
    for rpm in (0.0, 0.5 * step, step, top_prem):
        f = avg.dc_form(rpm * RPM, load)
        print(f"  averaged model at {rpm:5.0f} rpm: R_e = {f.r_line_ohm:.4g} ohm ({f.r_line_ohm / m.r_line_ohm:.2f} R), "
              f"L/R_e = {1e3 * m.l_line_h / f.r_line_ohm:.3g} ms, Kb' = {f.kb_v_s_per_rad:.4g} (DC {m.kb_v_s_per_rad:.4g}) "
              f"V s/rad, Kt' = {f.kt_n_m_per_a:.4g} N m/A")
    print(f"  kc below -R (1 - eps) = {-m.r_line_ohm * (1 - eps):.4g} ohm leaves the DC plant's current mode unstable")
    print("| model | disk rad/s | LMI | gamma | kp / kc / ki per rule | radius DC plant (worst at) | radius averaged plant (worst at) |")
    print("|---|---:|---|---:|---|---|---|")
    top = math.pi / 2 * prof.control.speed_loop_hz
    probe = None
    for plant_model in ("averaged", "six-step"):
        for k in range(n_disks):
            disk = top * 0.8 ** k
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                res = run_design(prof, "fuzzy-hinf", progress=False, simulate=False, plant_model=plant_model,
                                 pole_disk_rad_s=disk)
            cert = res.certificate
            label = "averaged" if plant_model == "averaged" else "DC equiv."
            if res.law is None:
                print(f"| {label} | {disk:.0f} | infeasible ({cert.get('solver_status', '')[:40]}) | | | | |")
                continue
            lmi = "feasible" + (" (SDP point kept: re-solve failed)" if "refinement" in cert else "")
            gains = "; ".join(f"{r.kp:.4g} / {r.kc:.4g} / {r.ki:.4g}" for r in res.law.rules)
            rd, wd = sampled_radius(prof, res.law)
            ra, wa = sampled_radius(prof, res.law,
                                    lambda w: SimpleNamespace(motor=avg.dc_form(w, load), inverter=prof.inverter))
            print(f"| {label} | {disk:.0f} | {lmi} | {cert['gamma']:.4g} | {gains} | {rd:.4f} ({wd}) | {ra:.4f} ({wa}) |")
            if plant_model == "averaged" and probe is None and rd > 0.95 >= ra:
                probe = (disk, res.law, rd, ra)
    if probe is None:
        print("  (no averaged-model disk passes on the averaged plant and fails on the DC plant)")
        return
    disk, law, rd, ra = probe
    plan = sim_plan(prof)
    print(f"  three-phase plant, averaged-model law of the {disk:.0f} rad/s disk (radius {rd:.3f} DC / {ra:.3f} "
          f"averaged), the verification's step to {plan['target_rpm']:.0f} rpm and load step:")
    for rs in (1.0 - eps, 1.0, 1.0 + eps):
        sim = run_sim(prof, law, plan, measurement=speed_measurement(prof, law), disturbances=False,
                      three_phase=lambda p, rf=1.0, rs=rs: three_phase_plant(p, rf * rs))
        f = step_figures(sim, plan, prof)
        print(f"    R x {rs:g}: rise {1e3 * f['rise_s']:.1f} ms, settling {1e3 * f['settling_s']:.0f} ms, overshoot "
              f"{f['overshoot_pct']:.2f} %, final error {f['final_error_rpm']:.2f} rpm, load dip {f['load_dip_rpm']:.1f} rpm, "
              f"peak current {f['peak_current_a']:.2f} A")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("names", nargs="*", help=f"corpus profile names or .toml paths (default {', '.join(DEFAULT)})")
    ap.add_argument("--disks", type=int, default=12, help="how many disks of the search (default 12)")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    for n in args.names or DEFAULT:
        run(n, args.disks)
    print(f"\n{time.perf_counter() - t0:.0f} s wall")
    return 0


if __name__ == "__main__":
    sys.exit(main())
