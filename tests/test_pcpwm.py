"""PCPWM plan: PTPER, DTCON, duty limit, commutation table against a hand-derived six-step table."""
import math

import pytest

from picdrive.firmware import pcpwm
from picdrive.profile import load_profile

# Hand-derived (docs/firmware.md convention): 120-degree halls whose edges sit
# exactly at the commutation points (hall A rising 30 deg after e_a's rising
# zero).  Sector [30, 90): halls A=1 B=0 C=1 -> code 101, phase A has the top
# of its flat +1 and B the bottom of its flat -1 -> A+ B-; and so on round
# the circle in 60-degree steps.
HAND_FORWARD = {0b101: "A+B-", 0b001: "A+C-", 0b011: "B+C-", 0b010: "B+A-", 0b110: "C+A-", 0b100: "C+B-"}
HAND_REVERSE = {0b101: "B+A-", 0b001: "C+A-", 0b011: "C+B-", 0b010: "A+B-", 0b110: "A+C-", 0b100: "B+C-"}
# register values: high side of the source phase follows the duty (POVD odd = 1),
# low side of the sink phase forced on (POVD even = 0, POUT even = 1)
HAND_REGS = {"A+B-": (0x02, 0x04), "A+C-": (0x02, 0x10), "B+C-": (0x08, 0x10),
             "B+A-": (0x08, 0x01), "C+A-": (0x20, 0x01), "C+B-": (0x20, 0x04)}


@pytest.mark.parametrize("shape", ["trapezoidal", "sinusoidal"])
def test_table_matches_hand_derived_six_step(shape):
    t = pcpwm.commutation_table(120, 30.0, shape)
    for code in range(8):
        if code in (0, 7):
            assert t.forward[code] is None and t.reverse[code] is None
            assert t.ovdcond[0][code] == t.ovdcons[0][code] == 0
            continue
        assert t.describe(code, 0) == HAND_FORWARD[code]
        assert t.describe(code, 1) == HAND_REVERSE[code]
        assert (t.ovdcond[0][code], t.ovdcons[0][code]) == HAND_REGS[HAND_FORWARD[code]]
        assert (t.ovdcond[1][code], t.ovdcons[1][code]) == HAND_REGS[HAND_REVERSE[code]]
    assert t.valid_mask == 0b01111110
    # forward rotation visits 101, 001, 011, 010, 110, 100 (cyclically)
    seq = list(t.sequence)
    i = seq.index(0b101)
    assert seq[i:] + seq[:i] == [0b101, 0b001, 0b011, 0b010, 0b110, 0b100]


def test_offset_shifts_the_table_by_whole_sectors():
    base = pcpwm.commutation_table(120, 30.0)
    shifted = pcpwm.commutation_table(120, 90.0)   # halls 60 deg later
    nxt = {0b101: 0b001, 0b001: 0b011, 0b011: 0b010, 0b010: 0b110, 0b110: 0b100, 0b100: 0b101}
    for code, after in nxt.items():
        # a code is now seen one sector later in angle, where the base table applies the next code's state
        assert shifted.describe(code) == base.describe(after)
        assert shifted.describe(code, 1) == base.describe(after, 1)


def test_tie_breaks_towards_phase_advance():
    # offset 0: each hall sector straddles two commutation sectors; forward picks the later one
    t0 = pcpwm.commutation_table(120, 0.0)
    t30 = pcpwm.commutation_table(120, 30.0)
    assert t0.forward == t30.forward
    assert t0.describe(0b101, 1) == "B+C-"     # reverse rotation advances the other way


def test_sixty_degree_halls():
    t = pcpwm.commutation_table(60, 30.0)
    assert t.forward[0b010] is None and t.forward[0b101] is None
    assert t.forward[0] is not None and t.forward[7] is not None
    assert len(set(t.forward[c] for c in range(8) if t.forward[c])) == 6
    # equivalence: 60-degree code with B inverted, B/C swapped is the 120-degree code
    t120 = pcpwm.commutation_table(120, 30.0)
    for code in range(8):
        if t.forward[code] is None:
            continue
        a, b, c = code & 1, code >> 1 & 1, code >> 2 & 1
        equiv = a | (c << 1) | ((1 - b) << 2)
        assert t.forward[code] == t120.forward[equiv]


def test_pwm_period_and_resolution():
    p = pcpwm.pwm_period(20000)
    assert (p.ptper, p.prescale) == (499, 1) and p.frequency_hz == 20000.0
    assert p.duty_full_counts == 2000 and p.duty_resolution_bits == pytest.approx(math.log2(2000))
    p = pcpwm.pwm_period(1000)                  # 10000 counts do not fit 12 bits at 1:1
    assert (p.ptper, p.prescale, p.ptckps) == (2499, 4, 1)
    p = pcpwm.pwm_period(17000)
    assert p.ptper == 587 and abs(p.frequency_hz - 17000) / 17000 < 1e-3
    with pytest.raises(pcpwm.PwmError, match="slowest PCPWM period"):
        pcpwm.pwm_period(20)
    with pytest.raises(pcpwm.PwmError, match="fewer than 100 duty steps"):
        pcpwm.pwm_period(500000)


def test_dead_time_prescaler_and_rounding():
    d = pcpwm.dead_time(1000)
    assert (d.dtps, d.dt, d.dtcon, d.dead_time_ns) == (0, 20, 0x14, 1000.0)
    d = pcpwm.dead_time(500)       # 0b01000101 would be 500 ns too; the finest prescaler is chosen
    assert d.dead_time_ns == 500 and d.dtps == 0
    d = pcpwm.dead_time(4010)      # > 63 x 50 ns -> 100 ns ticks, rounded up
    assert (d.dtps, d.dt, d.dead_time_ns) == (1, 41, 4100.0)
    d = pcpwm.dead_time(10000)
    assert d.dtps == 2 and d.dead_time_ns == 10000
    with pytest.raises(pcpwm.PwmError, match="longest dead time"):
        pcpwm.dead_time(30000)


def test_duty_limit_and_impossible_combination():
    prof = load_profile("duy2008")
    plan = pcpwm.plan_pwm(prof)
    assert plan.max_duty == pytest.approx(prof.max_duty()) and plan.pdc_max == 1840
    per, dt = pcpwm.pwm_period(100000), pcpwm.dead_time(2000)
    with pytest.raises(pcpwm.PwmError, match="less than half"):
        pcpwm.duty_limit(per, dt, 2000.0)
    # achieved dead time rounds up: the limit uses it
    per, dt = pcpwm.pwm_period(20000), pcpwm.dead_time(1010)
    md, counts = pcpwm.duty_limit(per, dt, 2000.0)
    assert dt.dead_time_ns == 1050 and counts == math.floor((1 - 4100 / 50000) * 2000)
