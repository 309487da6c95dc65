"""A landing that knows the load: the integrator at the current window's exit set from a load estimate
(a float-law study; docs/scheduling.md section 3, "A landing that knows the load").

The bundled designs (examples/*.design.json), loads 0 and the profile's load from t = 0, the step of
bench/time_optimal.py (its functions: the verification's plant, ``simulate_six_step`` with the
three-phase winding and the firmware's speed measurement; ratio design / bound, overshoot of the
sector-mean speed), five laws:

* today: the bundled law (``control_law.law_step``);
* preload: the reference feedforward (``design.verify.with_reference_ff``: ``G_ff dr`` into the
  integrator on each reference change);
* hold: the preload, then no integration until the error changes sign or the speed stops approaching
  within half the step (the hold of docs/scheduling.md section 3, re-implemented here);
* landing: the bundled law plus, after a reference change and while the output sits on the window's
  top, the integrator set (back-calculation) to ``G_ff r + (R_L + Kc) i_L``: the no-load steady state
  at the reference (with the setpoint-weight and current-feedback terms, ``reference_ff_gain``) plus
  the load's share, from a load-current estimate the firmware could make from what it measures::

      x    = i - (J / kt) (y - y_prev) / Ts - (i_ss / w_s) y     measured current minus acceleration and
      i_L += a (x - i_L)                                          no-load current; first-order filter

  (``kt`` the averaged model's torque per sensed ampere and ``i_ss`` its no-load current, both at the
  step speed ``w_s``; ``R_L`` the averaged model's voltage per ampere of load current there, the secant
  from no load to the profile's load).  At the window's exit the normal conditional integration takes
  over; a constant reference never arms it, so the load rejection is the law's own;
* landing+hold: the landing, then after the release no integration until the hold ends (the hold
  variant's rule), with the integrator holding the load-aware value.

Per profile and load, the floor of the measure: the bound's own speed profile
(``timeoptimal.measured_bound``) measured as the designs are (sector-mean speed, a centred mean over one
hall sector, into the 1 % band).  Besides the steps: the load dip of the profile's load step
(``time_optimal.load_dip``) with each law, and with ``--rates`` the same laws at 2 and 5 kHz (the
law's sample time changed, gains unchanged: Ki Ts and Kd / Ts are per second already).  The laws are substituted for ``picdrive.models.simulate.law_step`` only inside
this script.

    PYTHONPATH=$PWD/host:$PWD/hil python3 bench/landing.py [--rates] [--tau-ms 8] [--only NAME]
"""
from __future__ import annotations

import argparse
import contextlib
import dataclasses
import math
import sys
import warnings
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import time_optimal  # noqa: E402  (bench/time_optimal.py: load_dip)
from picdrive.analysis.timeoptimal import law_step_to_band, measured_bound  # noqa: E402
from picdrive.design.verify import with_reference_ff  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


@contextlib.contextmanager
def law_substituted(step):
    """Run ``simulate_six_step`` with ``step`` (same signature as ``control_law.law_step``) as its law."""
    from picdrive.models import simulate
    if step is None:
        yield
        return
    old = simulate.law_step
    simulate.law_step = step
    try:
        yield
    finally:
        simulate.law_step = old


def _q(law, st, r: float, y: float, i: float) -> float:
    """The law's output without the integral (P + D - Kc i) after ``law_step`` ran this sample (its D state)."""
    g = law.gains_at(y)
    return g.kp * (law.setpoint_weight * r - y) + st.d_filt_v - g.kc * i


def _arm_hold(st, r: float, r_prev: float) -> None:
    """A reference change arms the hold: the step's sign and half its size."""
    st.h_armed, st.h_sign, st.h_half, st.h_e = True, math.copysign(1.0, r - r_prev), 0.5 * abs(r - r_prev), None


def _hold_over(st, e: float) -> bool:
    """The hold ends when the error changes sign or, within half the step, the speed stops approaching."""
    approaching = st.h_e is None or abs(e) < abs(st.h_e)
    st.h_e = e
    return e * st.h_sign <= 0.0 or (abs(e) < st.h_half and not approaching)


def _held(law, st, r, y, i, integ: float) -> float:
    """The output with the integrator set to ``integ`` (clamped to its range) this sample."""
    lim = law.i_lim_v
    st.integ_v = min(max(integ, -lim), lim)
    lo, hi = law.output_limits(y)
    return min(max(_q(law, st, r, y, i) + st.integ_v, lo), hi)


def hold_step(law_ff):
    """The preload, then no integration until the hold ends (``_hold_over``; ``law_ff`` carries G_ff)."""
    from picdrive.control_law import law_step

    def step(law, st, r, y, i):
        if r != getattr(st, "h_r", 0.0):
            _arm_hold(st, r, getattr(st, "h_r", 0.0))
            st.h_r = r
        i0 = st.integ_v
        dr = r - st.r_prev
        u = law_step(law, st, r, y, i)
        if st.h_armed:
            if _hold_over(st, r - y):
                st.h_armed = False
            else:
                u = _held(law, st, r, y, i, i0 + law.reference_ff_v_s_per_rad * dr)
        return u
    return step


@dataclasses.dataclass(frozen=True)
class Landing:
    """The landing's constants (SI), as the firmware would hold them."""

    g_ff: float            # V per rad/s: no-load integrator per rad/s of reference (reference_ff_gain)
    k_load: float          # V per A of load current: R_L + Kc (Kc blended at the step speed)
    j_over_kt: float       # A per rad/s^2
    i0_per_w: float        # A per rad/s: no-load current per speed
    tau_s: float           # estimator's filter time constant


def landing_constants(profile, law, avg, tau_s: float) -> Landing:
    from picdrive.control_law import reference_ff_gain
    w = profile.speed_step_rpm() * math.pi / 30.0
    tl = profile.control.load_torque_n_m
    u0, i0 = avg.equilibrium(w, 0.0)
    u1, i1 = avg.equilibrium(w, tl)
    return Landing(g_ff=reference_ff_gain(law, w, u0, i0), k_load=(u1 - u0) / (i1 - i0) + law.gains_at(w).kc,
                   j_over_kt=avg.j_kg_m2 / avg.kt(w), i0_per_w=i0 / w, tau_s=tau_s)


def landing_step(c: Landing, trace: list | None = None, hold: bool = False):
    """The bundled law plus the load-aware landing (module docstring); ``hold``: after the release the
    integrator also holds its value until the hold ends (``_hold_over``), as the hold variant does."""
    from picdrive.control_law import law_step

    def step(law, st, r, y, i):
        ts = law.sample_time_s
        if not hasattr(st, "l_est"):
            st.l_est, st.l_y, st.l_r, st.l_armed, st.h_armed = 0.0, y, 0.0, False, False
        x = i - c.j_over_kt * (y - st.l_y) / ts - c.i0_per_w * y
        st.l_est += ts / (ts + c.tau_s) * (x - st.l_est)
        st.l_y = y
        if r != st.l_r:
            st.l_armed = r > st.l_r          # steps up: the output sits on the window's top
            _arm_hold(st, r, st.l_r)
            st.h_armed = st.h_armed and hold and st.l_armed
            st.l_r = r
        i0 = st.integ_v
        u = law_step(law, st, r, y, i)
        if st.l_armed:
            if r - y <= 0.0:
                st.l_armed = st.h_armed = False
            else:
                u = _held(law, st, r, y, i, c.g_ff * r + c.k_load * max(0.0, st.l_est))
                lo, hi = law.output_limits(y)
                if u < hi:                     # released: conditional integration (or the hold) from here on
                    st.l_armed = False
                    if trace is not None:
                        trace.append((y, st.l_est, st.integ_v))
        elif st.h_armed:
            if _hold_over(st, r - y):
                st.h_armed = False
            else:
                u = _held(law, st, r, y, i, i0)
        return u
    return step


def run_case(p, law, step, drive, load, rpm, bound_s) -> dict:
    with law_substituted(step):
        d = law_step_to_band(p, law, drive, load, rpm)
    return {"ratio": d["t_band_s"] / bound_s, "ovs": d["overshoot_pct"], "ms": 1e3 * d["t_band_s"]}


def variants(p, law, drive, avg, tau_s, trace=None):
    lf = with_reference_ff(p, law, drive)
    return {"today": (law, None), "preload": (lf, None), "hold": (lf, hold_step(lf)),
            "landing": (law, landing_step(landing_constants(p, law, avg, tau_s), trace)),
            "landing+hold": (law, landing_step(landing_constants(p, law, avg, tau_s), hold=True))}


def main(argv):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tau-ms", type=float, default=8.0, help="load estimator's filter time constant, ms")
    ap.add_argument("--rates", action="store_true", help="also run every law at 2 and 5 kHz")
    ap.add_argument("--only", default="", help="substring of the design names to run")
    a = ap.parse_args(argv)
    from picdrive.analysis.steptest import sector_period_s
    from picdrive.analysis.timeoptimal import time_to_band
    from picdrive.gate import BuiltDrive, three_phase_plant
    from picdrive.models.averaged import identify
    from picdrive.profile import load_profile
    from picdrive.result import load_design
    warnings.simplefilter("ignore")
    drive = BuiltDrive()
    print(f"estimator filter tau {a.tau_ms} ms; per law: ratio design/bound (overshoot % of the sector mean)")
    for prof_name in ("duy2008", "assawinchaichote2016"):
        p = load_profile(str(ROOT / f"examples/{prof_name}.toml"))
        avg = identify(p, three_phase_plant)
        rpm = p.speed_step_rpm()
        w_t = rpm * math.pi / 30.0
        bounds = {ld: time_to_band(p, w_t, ld, model=avg)["t_s"] for ld in (0.0, p.control.load_torque_n_m)}
        for ld, b in bounds.items():
            # the bound's own speed profile measured as the designs are (sector mean, 1 % band): the
            # ratio a perfect bang-bang-then-hold law scores under this measure
            floors = [f"{measured_bound(p, w_t, ld, model=avg, ts=1.0 / hz) / b:.2f} at {hz:.0f} Hz"
                      for hz in (1000.0, 5000.0)]
            print(f"{prof_name} load {ld:6.3g}: bound {1e3 * b:.1f} ms; the bound's trajectory, sector mean "
                  f"({1e3 * sector_period_s(p, rpm):.1f} ms window): ratio " + ", ".join(floors), flush=True)
        for path in sorted((ROOT / "examples").glob(f"{prof_name}.*.design.json")):
            name = path.name[:-12]
            res = load_design(str(path))
            if res.law is None or a.only not in name:
                continue
            rates = (None, 2000.0, 5000.0) if a.rates else (None,)
            for hz in rates:
                law = res.law if hz is None else dataclasses.replace(res.law, sample_time_s=1.0 / hz)
                for load, b in bounds.items():
                    trace = []
                    cells = []
                    for n, (lw, st) in variants(p, law, drive, avg, 1e-3 * a.tau_ms, trace).items():
                        f = run_case(p, lw, st, drive, load, rpm, b)
                        cells.append(f"{n} {f['ratio']:5.2f} ({f['ovs']:4.2f})")
                    rel = "" if not trace else (f" | release at {trace[0][0] * 30 / math.pi:.0f} rpm, "
                                                f"i_L est {trace[0][1]:.3f} A, I {trace[0][2]:.2f} V")
                    hzs = f"{1 / law.sample_time_s:5.0f} Hz"
                    print(f"{name:30} {hzs} load {load:6.3g} | " + "  ".join(cells) + rel, flush=True)
                if hz is None:
                    dips = []
                    for n, (lw, st) in variants(p, law, drive, avg, 1e-3 * a.tau_ms).items():
                        with law_substituted(st):
                            dd = time_optimal.load_dip(p, lw, drive, rpm)
                        dips.append(f"{n} {dd['dip_rpm']:.1f} rpm / {1e3 * dd['recovery_s']:.0f} ms")
                    print(f"{name:30} load step dip / back in 1 %: " + "  ".join(dips), flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
