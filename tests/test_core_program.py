"""The speed-loop law described once (picdrive.firmware.core_program): the model, the C and the
PIC18 assembly are rendered from one program, so one edit of it changes all three; every
operation states its overflow contract and has the three forms.  (The rendered C and assembly
against the model on random vectors: tests/test_fixedpoint.py on gcc, tests/test_target_bitexact.py
on the chip.)"""
import dataclasses
import random

import pytest

from picdrive.firmware import core_program as cp, fixedpoint as fx, pcpwm
from picdrive.control_law import Rule, ScheduledLaw
from picdrive.profile import load_profile

RPM = 3.141592653589793 / 30
PROFILE = load_profile("duy2008")


def _plan(nr=2, dfilt=False, ff=False):
    rules = tuple(Rule(0.2 - 0.01 * j, 5.0 - 0.3 * j, 0.0, 10.0 - j) for j in range(nr))
    law = ScheduledLaw(rules=rules, premise_rad_s=(0.0, 2600 * RPM), sample_time_s=1e-3, u_min_v=-44.16,
                       u_max_v=44.16, derivative_filter_hz=200.0 if dfilt else None,
                       reference_ff_v_s_per_rad=0.1 if ff else 0.0)
    return fx.plan_fixed_point(PROFILE, law, pcpwm.plan_pwm(PROFILE))


def _ops(steps, inner=("then", "orelse", "body", "STEPS")):
    for op in steps:
        yield op
        for name in inner:
            yield from _ops(getattr(op, name, ()), inner)


def _law_outputs(law_step, plan, n=3000, seed=5):
    rng = random.Random(seed)
    p = fx.law_params_from_plan(plan)
    out = []
    for _ in range(n):
        st = fx.LawState(integ=rng.randint(-2 ** 31, 2 ** 31 - 1), d_filt=rng.randint(-2 ** 20, 2 ** 20),
                         y_prev=rng.randint(-32768, 32767), primed=rng.randint(0, 1))
        r, y, i = (rng.randint(-32768, 32767) for _ in range(3))
        out.append((law_step(plan, p, st, r, y, i, p.u_min, p.u_max), st.integ))
    return out


def test_every_operation_has_a_contract_and_three_forms():
    """Every operation: a contract, a C and a Python form; those the assembly emitter reaches (all
    but the inner steps of a composite such as Headroom, whose assembly is the composite's) an
    assembly form."""
    kinds = {type(op) for fn in (cp.LAW, cp.CONTROL, cp.SPEED_HALL) for op in _ops(fn.steps)}
    emitted = {type(op) for fn in (cp.LAW, cp.CONTROL) for op in _ops(fn.steps, ("then", "orelse", "body"))}
    emitted -= {cp.MulQ15}     # the derivative filter: plans with it run SDCC's C law, not the assembly
    assert len(kinds) > 23 and len(emitted) > 15
    for k in kinds:
        assert k.contract, k.__name__                    # the overflow behaviour is stated
        for form in ("c", "py") + (("asm",) if k in emitted else ()):
            assert getattr(k, form) is not getattr(cp.Op, form), (k.__name__, form)


def test_the_model_is_the_program():
    """fixedpoint's law_step, core_control and speed_hall are the functions compiled from the programs."""
    assert fx.speed_hall.__code__.co_filename == "<core_program core_speed_hall>"
    assert fx.law_step.__code__.co_filename == "<core_program core_law>"
    assert fx.core_control.__code__.co_filename == "<core_program core_control>"
    plan = _plan()
    fresh = cp.model({"sat32": fx.sat32, "shift32": fx.shift32, "shl_sat32": fx.shl_sat32,
                      "duty_counts": fx.duty_counts})["law_step"]
    assert _law_outputs(fresh, plan) == _law_outputs(fx.law_step, plan)


@pytest.mark.parametrize("nr", [1, 2])
def test_one_edit_changes_the_model_the_c_and_the_assembly(nr):
    """A shift of the description changed by one (b r / 2^14 -> 2^15) changes the Python model's
    outputs, the C's ACC_ASR and the assembly's shift, and nothing else in the C."""
    plan = _plan(nr)
    bad = dataclasses.replace(cp.LAW, steps=tuple(cp.Asr(15) if op == cp.Asr(14) else op for op in cp.LAW.steps))
    assert bad.steps != cp.LAW.steps
    prims = {"sat32": fx.sat32, "shift32": fx.shift32, "shl_sat32": fx.shl_sat32, "duty_counts": fx.duty_counts}
    assert _law_outputs(cp.model(prims, (bad,))["law_step"], plan) != _law_outputs(fx.law_step, plan)
    c0, c1 = cp.c_source(cp.LAW).splitlines(), cp.c_source(bad).splitlines()
    assert [(a, b) for a, b in zip(c0, c1) if a != b] == [("    ACC_ASR(14);", "    ACC_ASR(15);")]
    bits = {"STATUS": {"Z": 2}}
    a0, a1 = cp.asm_source(cp.LAW, plan, bits), cp.asm_source(bad, plan, bits)
    assert a0 != a1 and cp.asr_asm(14) != cp.asr_asm(15)
    assert "\n".join(cp.asr_asm(14)) in a0 and "\n".join(cp.asr_asm(15)) in a1


def test_the_assembly_law_holds_at_most_two_rules():
    with pytest.raises(NotImplementedError, match="at most 2 rules"):
        cp.asm_source(cp.LAW, _plan(3), {"STATUS": {"Z": 2}})


@pytest.mark.parametrize("over", [False, True])
def test_the_drive_rules_are_the_same_on_volts_and_counts(over):
    """walk_cap and direction_hold (control_law): the firmware's integer rule and the averaged
    simulation's float one are one function."""
    from picdrive.control_law import direction_hold, walk_cap
    for cap in range(0, 101):
        assert walk_cap(cap, over, 7, 100) == (max(0, cap - 7) if over else min(100, cap + 7))
        assert walk_cap(float(cap), over, 7.0, 100.0) == float(walk_cap(cap, over, 7, 100))
    assert direction_hold(-3, 0) == (1, True) and direction_hold(0, 1) == (1, False)
    assert direction_hold(5, 1) == (0, True) and direction_hold(5, 0) == (0, False)


def test_repeated_steps_get_their_own_labels():
    """The same clamp twice (and a 16-bit load stored without a sum) still assembles: labels are
    numbered per function, the pending load is sign-extended before the store."""
    law = dataclasses.replace(cp.LAW, steps=cp.LAW.steps[:-1] + (
        cp.Clamp("l.q", "I_LIM"), cp.Load("s.speed"), cp.Store("s.law.y_prev"), cp.LAW.steps[-1]))
    text = cp.asm_source(law, _plan(2), {"STATUS": {"Z": 2}})
    labels = [ln[:-1] for ln in text.splitlines() if ln.endswith(":")]
    assert len(labels) == len(set(labels)) and "law_not_hi_2" in labels
    i = text.index("law_lim_done_2:")
    assert "CALL    _core_acc_sext_ab" in text[i:text.index("law_not_min:")]
