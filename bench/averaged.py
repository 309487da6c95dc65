"""The speed-dependent averaged six-step model (picdrive.models.averaged) against the twin's plant.

For each bundled profile: identify the model from the motor twin's three-phase plant (speed held,
a few duties per speed), then at 5 speeds (10, 30, 50, 75, 95 % of the step target) and 2 loads
(none, the profile's load) run the same plant free (open loop, hall table, the firmware's bridge
rule) at the voltage the model says holds the speed, step that voltage by -5 %, and print
steady speed, mean sensed current, small-signal gain and 63 % time: twin, averaged model, DC
equivalent (2008 eq 1), and the model's and the DC equivalent's errors.

    PYTHONPATH=$PWD/host:$PWD/hil python3 bench/averaged.py [profile.toml ...]
"""
from __future__ import annotations

import sys
import time
import warnings
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def main(argv):
    from picdrive.analysis.modelcheck import check_point
    from picdrive.gate import three_phase_plant
    from picdrive.models.averaged import identify
    from picdrive.profile import load_profile
    warnings.simplefilter("ignore")
    paths = argv or [str(ROOT / "examples/duy2008.toml"), str(ROOT / "examples/assawinchaichote2016.toml")]
    for path in paths:
        p = load_profile(path)
        t0 = time.perf_counter()
        mdl = identify(p, three_phase_plant)
        print(f"\n== {p.name}: step target {p.speed_step_rpm():.0f} rpm, L/R {1e3 * p.motor.l_line_h / p.motor.r_line_ohm:.3g} ms, "
              f"hall offset {p.sensors.hall_offset_deg:g} deg; identified in {time.perf_counter() - t0:.1f} s")
        print("   rpm    R_e ohm   E/(Kb w)   k_t/Kt   T_0 N m    fit rms A")
        for q in mdl.points:
            print(f"  {q.w_rad_s * 60 / 6.283185307:6.0f}  {q.r_e_ohm:8.3f}  {q.e_v / (p.motor.kb_v_s_per_rad * q.w_rad_s):8.4f}"
                  f"  {q.kt_n_m_per_a / p.motor.kt_n_m_per_a:8.4f}  {q.t0_n_m:+9.5f}  {q.fit_rms_a:9.2e}")
        print("   rpm  load  |  speed rpm: twin  model(err%)  dc(err%)  |  current A: twin  model(err%)  dc(err%)  |"
              "  gain rpm/V: twin  model(err%)  dc(err%)  |  t63 ms: twin  model(err%)  dc(err%)")
        top = p.speed_step_rpm()
        for f in (0.1, 0.3, 0.5, 0.75, 0.95):
            for load in (0.0, p.control.load_torque_n_m):
                c = check_point(p, mdl, three_phase_plant, f * top, load)
                tw, mo, dc = c["twin"], c["model"], c["dc"]

                def e(k, s):
                    return 100 * (s[k] - tw[k]) / tw[k]
                print(f"  {f * top:5.0f} {load:5.3g} | {tw['w_rpm']:8.1f} {mo['w_rpm']:7.1f}({e('w_rpm', mo):+5.2f})"
                      f" {dc['w_rpm']:7.1f}({e('w_rpm', dc):+5.1f}) | {tw['i_a']:7.4f} {mo['i_a']:7.4f}({e('i_a', mo):+5.1f})"
                      f" {dc['i_a']:7.4f}({e('i_a', dc):+5.1f}) | {tw['gain_rpm_per_v']:7.2f} {mo['gain_rpm_per_v']:7.2f}"
                      f"({e('gain_rpm_per_v', mo):+5.1f}) {dc['gain_rpm_per_v']:7.2f}({e('gain_rpm_per_v', dc):+5.1f})"
                      f" | {1e3 * tw['t63_s']:6.2f} {1e3 * mo['t63_s']:6.2f}({e('t63_s', mo):+5.1f})"
                      f" {1e3 * dc['t63_s']:6.2f}({e('t63_s', dc):+5.1f})", flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
