"""Speed steps down: 2400 -> 600 rpm and to rest, against the friction-only coast.

For each bundled duy2008 design (and the 2016 designs, from their step target to a quarter of it
and to rest): the law in the verification's plant (the twin's three-phase winding, the firmware's
speed measurement and current window, picdrive.models.simulate.simulate_six_step) runs at the high
speed, then the reference drops.  Printed: the time until the sector-mean speed stays within 2 % of
the new reference (to rest: until the speed stays below 2 % of the start), the least current the law
drew (negative: the reverse table, plugging), and the same plant coasting with every switch off
(friction and load only: the first time it is within 2 % of the new reference, or below 2 % of the
start for rest; the analytic J/B ln((B w0 + T)/(B w1 + T)) beside), with and without the profile's
load (passive: it stops the rotor); and the bound of braking at the current limit all the way down
(J w' = -Kt I_lim - B w - T_load), what a bridge that can reverse the current below the back-EMF allows;
and the same plant braked by a low-side braking table (low_side_brake_run: the scheme docs/scheduling.md
proposes for the PIC18F4431, open loop at the current window's braking edge), its peak phase current
and the energy it returns to the bus; beside each run the peak DC-bus voltage (the plant's bus
capacitor, ``inverter.bus_capacitance_f``, behind a supply that cannot sink current).

    PYTHONPATH=$PWD/host:$PWD/hil python3 bench/step_down.py
"""
from __future__ import annotations

import math
import sys
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def settle_after(t, y, t0, goal, band_abs):
    sel = t >= t0
    tt, yy = t[sel], y[sel]
    out = np.nonzero(np.abs(yy - goal) > band_abs)[0]
    if out.size == 0:
        return 0.0
    if out[-1] == yy.size - 1:
        return math.inf
    return float(tt[out[-1] + 1] - t0)


def first_below(t, y, level):
    hit = np.nonzero(y <= level)[0]
    return float(t[hit[0]]) if hit.size else math.inf


def coast_s(profile, w0, w1, load):
    """Friction-only coast from w0 to w1 (rad/s): J w' = -B w - T_load, s."""
    m = profile.motor
    J, B = m.inertia_kg_m2, m.viscous_friction_n_m_s
    return J / B * math.log((B * w0 + load) / (B * w1 + load))


def brake_bound_s(profile, w0, w1, load):
    """Braking at the current limit the whole way (what a bridge that can reverse the current below the
    back-EMF would allow): J w' = -Kt I_lim - B w - T_load, s."""
    m = profile.motor
    J, B = m.inertia_kg_m2, m.viscous_friction_n_m_s
    tb = m.kt_n_m_per_a * profile.inverter.current_limit_a + load
    return J / B * math.log((B * w0 + tb) / (B * w1 + tb))


def low_side_brake_run(profile, plant, w0: float, goal: float, load: float, t_max: float, *,
                       plug_below: bool = False) -> dict:
    """What a low-side braking table would give (docs/scheduling.md, section 4), in the twin's three-phase plant:
    on each hall code the forward table's source leg has its LOW side on for ``d`` of the period (PWM) and
    the sink's low side on, both high sides off (independent mode, no PMOD change); in the off-time the
    braking current returns through the source's high-side body diode into the bus.  ``d`` from the law's
    window: the average line voltage ``(1 - d) Vbus = max(0, Kb w - R I_lim)`` (braking current at the
    limit), applied from the true speed every PWM period, until ``w <= goal``; then every switch off.
    ``plug_below``: below ``R I_lim / Kb`` (where the window's braking edge is negative) plug instead: the
    reverse table with its source's high side at duty ``(R I_lim - Kb w)/Vbus``, as the law's window does.
    Returns the time to the goal (s), the peak phase current (A), the energy returned to the bus (J) and
    the peak bus voltage (V: the plant's capacitor behind a supply that cannot sink)."""
    from picdrive.commutation import hall_table
    m, inv, se = profile.motor, profile.inverter, profile.sensors
    ht = hall_table(se.hall_spacing_deg, se.hall_offset_deg, m.back_emf_shape)
    tab = ht.forward
    h = 1.0 / inv.pwm_frequency_hz
    plant.state.w_rad_s = w0
    t = e_bus = i_pk = 0.0
    v_pk = plant.state.v_bus_v
    while t < t_max:
        w = plant.state.w_rad_s
        if w <= goal:
            return {"t_s": t, "i_peak_a": i_pk, "e_bus_j": e_bus, "v_bus_peak_v": v_pk}
        u = m.kb_v_s_per_rad * w - m.r_line_ohm * inv.current_limit_a
        legs = [(0.0, 0.0)] * 3
        if u < 0.0 and plug_below:
            st = ht.reverse[plant.hall_code()]
            if st is not None:
                legs[st[0]] = (min(1.0, -u / inv.bus_voltage_v), 0.0)
                legs[st[1]] = (0.0, 1.0)
        else:
            d = min(1.0, max(0.0, 1.0 - max(u, 0.0) / inv.bus_voltage_v))
            st = tab[plant.hall_code()]
            if st is not None:
                legs[st[0]] = (0.0, d)
                legs[st[1]] = (0.0, 1.0)
        plant.step(legs, load if w > 0.0 else 0.0, h)
        t += h
        i_pk = max(i_pk, plant.state.i_peak_a)
        v_pk = max(v_pk, plant.state.v_bus_v)
        e_bus -= inv.bus_voltage_v * plant.state.i_bus_a * h
    return {"t_s": math.inf, "i_peak_a": i_pk, "e_bus_j": e_bus, "v_bus_peak_v": v_pk}


def main(argv):
    from picdrive.analysis.steptest import sector_mean
    from picdrive.gate import BuiltDrive, three_phase_plant
    from picdrive.models.averaged import open_loop_run
    from picdrive.models.simulate import simulate_six_step
    from picdrive.profile import load_profile
    from picdrive.result import load_design
    warnings.simplefilter("ignore")
    drive = BuiltDrive()
    print("design                         load   from->to rpm | law: settle ms  min current A  peak bus V | "
          "coast (all off) to the band: ms")
    for prof_name in ("duy2008", "assawinchaichote2016"):
        p = load_profile(str(ROOT / f"examples/{prof_name}.toml"))
        hi = min(2400.0, p.speed_step_rpm())
        for lo in (600.0 if hi == 2400.0 else round(hi / 4), 0.0):
            for load in (0.0, p.control.load_torque_n_m):
                t1 = 0.4
                goal = 1.02 * lo if lo > 0 else 0.02 * hi
                rad = 2 * math.pi / 60
                t_an = coast_s(p, hi * rad, goal * rad, load)
                t_end = t1 + min(20.0, max(1.0, 1.3 * t_an))
                # coast: the same plant at the high speed, every switch off: first time within the band
                run = open_loop_run(p, three_phase_plant(p, 1.0), lambda t: 0.0, t_end - t1, load,
                                    w0_rad_s=hi * rad)
                t_coast = first_below(run["t"], run["w"] / rad, goal)
                lsb = low_side_brake_run(p, three_phase_plant(p, 1.0), hi * rad, goal * rad, load, t_end - t1)
                lsp = low_side_brake_run(p, three_phase_plant(p, 1.0), hi * rad, goal * rad, load, t_end - t1,
                                         plug_below=True)
                for path in sorted((ROOT / "examples").glob(f"{prof_name}.*.design.json")):
                    res = load_design(str(path))
                    if res.law is None:
                        continue
                    sim = simulate_six_step(p, res.law, t_end=t_end, ref_rpm=lambda t: hi if t < t1 else lo,
                                            load=load, commutated=True, **drive.speed_measurement(p, res.law),
                                            three_phase=drive.three_phase_plant(p))
                    ts = res.law.sample_time_s
                    if lo > 0:
                        sm = sector_mean(p, sim.rpm, ts, lo, breaks=(int(round(t1 / ts)),))
                        t_s = settle_after(sim.t, sm, t1, lo, 0.02 * lo)
                    else:
                        t_s = settle_after(sim.t, sim.rpm, t1, 0.0, 0.02 * hi)
                    i_min = float(np.min(sim.i[sim.t >= t1]))
                    v_pk = float(np.max(sim.v_bus_fine[sim.t_fine >= t1]))
                    print(f"{path.name[:-12]:30} {load:5.3g} {hi:6.0f}->{lo:4.0f} | {1e3 * t_s:14.1f} {i_min:14.3f} "
                          f"{v_pk:11.1f} |"
                          f" {1e3 * t_coast:10.1f} (J/B ln: {1e3 * t_an:.1f}) | braking at I_lim: "
                          f"{1e3 * brake_bound_s(p, hi * rad, goal * rad, load):.1f} | low-side braking table: "
                          f"{1e3 * lsb['t_s']:.1f} ms, peak {lsb['i_peak_a']:.2f} A, to the bus {lsb['e_bus_j']:.3f} J, "
                          f"bus peak {lsb['v_bus_peak_v']:.1f} V"
                          f" | with plugging below R I_lim/Kb: {1e3 * lsp['t_s']:.1f} ms, peak {lsp['i_peak_a']:.2f} A, "
                          f"bus peak {lsp['v_bus_peak_v']:.1f} V",
                          flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
