"""The gcc/ctypes host harness of the bit-exact model: a generated folder's ``drive_core.c``
compiled by gcc into a shared library, driven through ctypes on random vectors beside
:mod:`picdrive.firmware.fixedpoint`'s model (0 LSB difference required).

Used by tests/test_fixedpoint.py, tests/test_target_bitexact.py (:func:`rand_params`, the
parameter generator the chip's comparison shares) and bench/firmware.py (10^5 vectors).  A
test harness, so it lives here and not in the package (docs/architecture.md, "The house").
"""
from __future__ import annotations

from picdrive.firmware.fixedpoint import (INT16_MAX, INT16_MIN, INT32_MAX, INT32_MIN, CoreState,
                                          FixedPointError, FixedPointPlan, LawParams, LawState,
                                          core_control, duty_counts, law_step, premise_k, sat16,
                                          speed_encoder, speed_hall)

__all__ = ["core_structs", "build_core_lib", "rand_params", "rand_law_state", "compare_with_c"]


def core_structs(n_rules: int, kff: bool = False):
    """ctypes mirrors of core_params_t, core_law_t, core_state_t for ``n_rules`` rules (``kff``: a
    build with the reference feedforward, core_s.ff), from picdrive.firmware.core_layout."""
    from picdrive.firmware import core_layout as L
    made: dict = {}
    defined = {"CORE_KFF"} if kff else set()
    return tuple(L.ctypes_struct(s, n_rules, defined, made) for s in (L.CORE_PARAMS, L.CORE_LAW, L.CORE_STATE))


def build_core_lib(folder, out_dir=None, cc: str = "gcc"):
    """Compile a generated folder's drive_core.c into a shared library and load it (ctypes)."""
    import ctypes as C
    import subprocess
    import tempfile
    from pathlib import Path
    folder = Path(folder)
    out = Path(out_dir or tempfile.mkdtemp(prefix="picdrive-core-"))
    out.mkdir(parents=True, exist_ok=True)
    lib = out / "libdrive_core.so"
    cmd = [cc, "-std=c99", "-Wall", "-Wextra", "-Werror", "-Wconversion", "-O1", "-shared", "-fPIC",
           f"-I{folder}", str(folder / "drive_core.c"), "-o", str(lib)]
    r = subprocess.run(cmd, capture_output=True, text=True)
    if r.returncode != 0:
        raise FixedPointError(f"drive_core.c does not compile: {r.stderr.strip()}")
    d = C.CDLL(str(lib))
    Params, Law, State = core_structs(_n_rules_of(folder), _kff_of(folder))
    # the C's parameters and state are globals (core_p, core_s): the functions take no pointers
    d.core_law.restype = None
    d.core_law.argtypes = []
    d.core_control.restype = None
    d.core_control.argtypes = [C.c_int16, C.c_uint16]
    # the firmware compiles the speed sensor's function only (FW_SPEED_ENCODER)
    if _speed_encoder_of(folder):
        d.core_speed_encoder.restype = None
        d.core_speed_encoder.argtypes = [C.c_uint16, C.c_uint16, C.c_uint8, C.c_uint8]
    else:
        d.core_speed_hall.restype = None
        d.core_speed_hall.argtypes = [C.c_uint16, C.c_uint16, C.c_uint8, C.c_uint8]
    d.core_duty.restype = C.c_uint16
    d.core_duty.argtypes = [C.c_int16]
    d.core_premise_k.restype = C.c_uint16
    d.core_premise_k.argtypes = [C.c_int16, C.c_int16]
    d.core_reset.restype = None
    d.core_reset.argtypes = []
    d.core_p = Params.in_dll(d, "core_p")
    d.core_s = State.in_dll(d, "core_s")
    d.structs = (Params, Law, State)
    return d


def _speed_encoder_of(folder) -> bool:
    import re
    from pathlib import Path
    m = re.search(r"#define FW_SPEED_ENCODER ([01])\n", (Path(folder) / "drive_params.h").read_text())
    if not m:
        raise FixedPointError(f"{folder}/drive_params.h has no FW_SPEED_ENCODER")
    return m.group(1) == "1"


def _kff_of(folder) -> bool:
    import re
    from pathlib import Path
    m = re.search(r"#define CORE_KFF (-?\d+)\n", (Path(folder) / "drive_params.h").read_text())
    if not m:
        raise FixedPointError(f"{folder}/drive_params.h has no CORE_KFF")
    return m.group(1) != "0"


def _n_rules_of(folder) -> int:
    import re
    from pathlib import Path
    m = re.search(r"#define CORE_N_RULES (\d+)u", (Path(folder) / "drive_params.h").read_text())
    if not m:
        raise FixedPointError(f"{folder}/drive_params.h has no CORE_N_RULES")
    return int(m.group(1))


def rand_params(plan: FixedPointPlan, rng, wide: bool) -> LawParams:
    nr = plan.n_rules

    def g(base):
        if wide:
            return [int(rng.integers(INT16_MIN, INT16_MAX + 1)) for _ in range(nr)]
        return [sat16(int(b * rng.uniform(0.0, 2.0)) + int(rng.integers(-3, 4))) for b in base]
    lo = int(rng.integers(0, 2000)) if not wide else int(rng.integers(0, INT16_MAX + 1))
    hi = int(rng.integers(lo, INT16_MAX + 1)) if rng.random() < 0.95 else int(rng.integers(0, INT16_MAX + 1))
    lim = plan.u_limit
    return LawParams(kp=g(plan.kp), kits=g(plan.kits), kdts=g(plan.kdts), kc=g(plan.kc),
                     premise_lo=lo, premise_hi=hi, mu_k=premise_k(lo, hi, nr, plan.mu_sh),
                     b_q14=int(rng.integers(0, INT16_MAX + 1)) if rng.random() < 0.5 else plan.b_q14,
                     u_min=int(rng.integers(-lim, 1)), u_max=int(rng.integers(0, lim + 1)),
                     controller=int(rng.integers(0, 2)), ilim=int(rng.integers(0, 1024)),
                     accel_step=int(rng.integers(0, 65536)) if rng.random() < 0.3 else 0)


def rand_law_state(rng, i_lim: int) -> LawState:
    if rng.random() < 0.7:
        integ = int(rng.integers(-i_lim, i_lim + 1))
    else:
        integ = int(rng.integers(INT32_MIN, INT32_MAX + 1))
    d = int(rng.integers(INT32_MIN, INT32_MAX + 1)) if rng.random() < 0.3 else int(rng.integers(-(1 << 20), 1 << 20))
    return LawState(integ=integ, d_filt=d, y_prev=int(rng.integers(INT16_MIN, INT16_MAX + 1)),
                    primed=int(rng.integers(0, 2)), mu1=0)


def _i16(rng, wide_p=0.3, span=None):
    if span is None or rng.random() < wide_p:
        return int(rng.integers(INT16_MIN, INT16_MAX + 1))
    return int(rng.integers(-span, span + 1))


def compare_with_c(plan: FixedPointPlan, lib, n: int, seed: int = 0) -> dict:
    """Run ``n`` random vectors of each core function through the Python model and the C.

    Returns ``{"vectors": total, "mismatches": count, "first": description or None}``
    per function and in total.  The vectors mix full-range values (every
    saturation path) with values around the design's own numbers.
    """
    import numpy as np
    rng = np.random.default_rng(seed)
    span_y = plan.to_speed_raw(1.5 * max(abs(plan.premise_hi) * 2.0 ** -plan.qs, 1.0))
    res = {"law": [0, 0, None], "control": [0, 0, None], "speed": [0, 0, None], "duty": [0, 0, None],
           "premise_k": [0, 0, None]}

    def fill_params(cp, p: LawParams):
        for j in range(plan.n_rules):
            cp.kp[j], cp.kits[j], cp.kdts[j], cp.kc[j] = p.kp[j], p.kits[j], p.kdts[j], p.kc[j]
        cp.premise_lo, cp.premise_hi, cp.mu_k, cp.b_q14 = p.premise_lo, p.premise_hi, p.mu_k, p.b_q14
        cp.u_min, cp.u_max, cp.controller, cp.ilim, cp.accel_step = p.u_min, p.u_max, p.controller, p.ilim, p.accel_step

    def law_to_c(cl, s: LawState):
        cl.integ, cl.d_filt, cl.y_prev, cl.primed, cl.mu1 = s.integ, s.d_filt, s.y_prev, s.primed, s.mu1

    def law_tuple(s):
        return (s.integ, s.d_filt, s.y_prev, s.primed, s.mu1)

    def note(key, ok, what):
        r = res[key]
        r[0] += 1
        if not ok:
            r[1] += 1
            if r[2] is None:
                r[2] = what

    cp, cs = lib.core_p, lib.core_s
    for k in range(n):
        wide = rng.random() < 0.3
        p = rand_params(plan, rng, wide)
        fill_params(cp, p)
        # premise slope
        note("premise_k", lib.core_premise_k(p.premise_lo, p.premise_hi) == p.mu_k,
             f"premise_k({p.premise_lo}, {p.premise_hi})")
        # the law
        umin, umax = p.u_min, p.u_max
        s = rand_law_state(rng, plan.i_lim)
        cl = cs.law
        law_to_c(cl, s)
        r_, y_ = _i16(rng, span=span_y), _i16(rng, span=span_y)
        i_ = _i16(rng, span=1023)
        cs.r_applied, cs.speed, cs.current, cs.umin, cs.umax = r_, y_, i_, umin, umax
        ff = 0
        if plan.kff:                                # the preload core_control would set, any int32
            ff = int(rng.choice([INT32_MIN, INT32_MAX, int(rng.integers(-2 ** 31, 2 ** 31)),
                                 int(rng.integers(-plan.i_lim, plan.i_lim + 1))]))
            cs.ff = ff
        lib.core_law()
        uc = cs.u
        up = law_step(plan, p, s, r_, y_, i_, umin, umax, ff)
        ok = uc == up and law_tuple(cl) == law_tuple(s)
        note("law", ok, f"law r={r_} y={y_} i={i_} ff={ff} params={p} -> C {uc} {law_tuple(cl)} Py {up} {law_tuple(s)}")
        # a whole control step (limiter, ramp, law, duty, direction)
        st = CoreState(law=rand_law_state(rng, plan.i_lim), speed_valid=int(rng.integers(0, 2)),
                       r_applied=_i16(rng, span=span_y), cap=int(rng.integers(0, plan.u_limit + 1)),
                       speed=_i16(rng, span=span_y), current=0, u=0, dir=int(rng.integers(0, 2)), hold=0, pdc=0)
        law_to_c(cs.law, st.law)
        cs.speed_valid, cs.r_applied, cs.cap, cs.speed = st.speed_valid, st.r_applied, st.cap, st.speed
        cs.current, cs.u, cs.dir, cs.hold, cs.pdc = 0, 0, st.dir, 0, 0
        target = _i16(rng, span=span_y)
        adc = int(rng.integers(0, 1024))
        lib.core_control(target, adc)
        uc = cs.u
        up = core_control(plan, p, st, target, adc)
        ok = (uc == up and law_tuple(cs.law) == law_tuple(st.law) and
              (cs.r_applied, cs.cap, cs.current, cs.u, cs.dir, cs.hold, cs.pdc) ==
              (st.r_applied, st.cap, st.current, st.u, st.dir, st.hold, st.pdc))
        note("control", ok, f"control target={target} adc={adc} -> C {uc} Py {up}")
        # speed measurement
        a16 = int(rng.integers(0, 65536))
        b16 = int(rng.integers(0, 65536)) if rng.random() < 0.5 else int(rng.integers(0, 200))
        prev_t5 = int(rng.integers(0, 65536))
        fl = [int(x) for x in rng.integers(0, 2, size=3)]
        valid0, wavg0 = int(rng.integers(0, 2)), _i16(rng, span=span_y)
        pos_prev = int(rng.integers(0, 65536))
        if rng.random() < 0.6:                      # small count steps, as at a real sample
            a16 = (pos_prev + int(rng.integers(-200, 201))) & 0xFFFF
        if rng.random() < 0.2:
            a16 = pos_prev
        t2, prev_t2 = (int(x) for x in rng.integers(0, 256, size=2))
        cs.speed_valid, cs.w_avg, cs.pos_prev, cs.t5_prev, cs.t2_prev = valid0, wavg0, pos_prev, prev_t5, prev_t2
        st2 = CoreState(speed_valid=valid0, w_avg=wavg0, pos_prev=pos_prev, t5_prev=prev_t5, t2_prev=prev_t2)
        if plan.speed_source == "encoder":
            lib.core_speed_encoder(a16, b16, t2, fl[0])
            wc = cs.speed
            wp = speed_encoder(plan, st2, a16, b16, t2, fl[0])
            ok = (wc == wp and (cs.speed_valid, cs.speed, cs.w_avg, cs.pos_prev, cs.t5_prev, cs.t2_prev) ==
                  (st2.speed_valid, st2.speed, st2.w_avg, st2.pos_prev, st2.t5_prev, st2.t2_prev))
            what = (f"speed pos={a16} t5={b16} t2={t2} ovf={fl[0]} "
                    f"prev=({valid0},{wavg0},{pos_prev},{prev_t5},{prev_t2})")
        else:
            lib.core_speed_hall(a16, b16, fl[0], fl[1])
            wc = cs.speed
            wp = speed_hall(plan, st2, a16, b16, fl[0], fl[1])
            ok = wc == wp and cs.speed == st2.speed
            what = f"hall speed period={a16} elapsed={b16} flags={fl}"
        note("speed", ok, f"{what} -> C {wc} Py {wp}")
        u = _i16(rng, span=plan.u_limit)
        note("duty", lib.core_duty(u) == duty_counts(plan, u), f"duty u={u}")
    total = sum(r[0] for r in res.values())
    bad = sum(r[1] for r in res.values())
    out = {k: {"vectors": v[0], "mismatches": v[1], "first": v[2]} for k, v in res.items()}
    out["total"] = {"vectors": total, "mismatches": bad,
                    "first": next((v[2] for v in res.values() if v[2]), None)}
    return out
