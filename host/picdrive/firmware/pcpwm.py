"""PCPWM of the PIC18F4431: PWM period, dead time, duty limit, hall commutation table.

Chip facts used (PIC18F2331/2431/4331/4431 data sheet, DS39616D, section 18):

* Fosc = 40 MHz (10 MHz crystal, HSPLL), Fcy = Fosc / 4 = 10 MHz.
* Edge-aligned (free-running) time base: ``T_pwm = (PTPER + 1) x PTMRPS /
  Fcy`` with the prescaler PTMRPS in {1, 4, 16, 64} (``PTCKPS1:0``) and
  PTPER 12 bits.  Duty = ``PDC / (4 (PTPER + 1))``: PDCx is 14 bits, its two
  low bits compare with the Q clocks.  Edge-aligned mode is used because it
  gives twice the duty resolution of centre-aligned mode at the same
  frequency, and six-step with one modulated switch gains nothing from
  centre alignment.
* DTCON: dead time = ``DT5:0 x`` tick, tick = 2, 4, 8 or 16 Tosc
  (``DTPS1:0`` = 00, 01, 10, 11: 50, 100, 200, 400 ns at 40 MHz).
* Independent mode with the output override (OVDCOND/OVDCONS) for six-step;
  odd outputs (PWM1/3/5) drive the high sides, even outputs the low sides;
  pair 0 = phase A, pair 1 = B, pair 2 = C (docs/firmware.md explains why
  not complementary mode).

Hall convention and the choice of drive state per hall code: :mod:`picdrive.commutation`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

from ..board import FCY_HZ, FOSC_HZ
from ..commutation import IDENT_VECTORS, PHASES, hall_table
from ..errors import PicdriveError

__all__ = ["PwmError", "FOSC_HZ", "FCY_HZ", "PwmPeriod", "DeadTime", "CommutationTable", "PwmPlan",
           "pwm_period", "dead_time", "duty_limit", "commutation_table", "drive_state_registers", "ident_vector_registers",
           "plan_pwm", "PHASES"]

_PTCKPS = {1: 0b00, 4: 0b01, 16: 0b10, 64: 0b11}
_DTPS_TOSC = {0b00: 2, 0b01: 4, 0b10: 8, 0b11: 16}


class PwmError(PicdriveError, ValueError):
    """The PWM frequency, dead time or hall placement cannot be realised."""


@dataclass(frozen=True)
class PwmPeriod:
    ptper: int                 # PTPERH:PTPERL (12 bits)
    prescale: int              # 1, 4, 16, 64
    ptckps: int                # PTCON0<3:2>
    frequency_hz: float        # achieved
    requested_hz: float

    @property
    def duty_full_counts(self) -> int:
        """PDC value for 100 % duty: 4 (PTPER + 1)."""
        return 4 * (self.ptper + 1)

    @property
    def duty_resolution_bits(self) -> float:
        return math.log2(self.duty_full_counts)

    @property
    def period_ns(self) -> float:
        return 1e9 / self.frequency_hz


@dataclass(frozen=True)
class DeadTime:
    dtcon: int                 # register value
    dtps: int                  # DTCON<7:6>
    dt: int                    # DTCON<5:0>
    dead_time_ns: float        # achieved (>= requested)
    requested_ns: float


def pwm_period(pwm_frequency_hz: float) -> PwmPeriod:
    """PTPER and prescaler for an edge-aligned PWM frequency (Hz).

    The smallest prescaler whose PTPER fits 12 bits (finest duty resolution),
    PTPER rounded to the nearest achievable period.
    """
    f = float(pwm_frequency_hz)
    if not (f > 0 and math.isfinite(f)):
        raise PwmError(f"PWM frequency {pwm_frequency_hz!r} Hz is not a positive number")
    for ps, bits in _PTCKPS.items():
        ptper = round(FCY_HZ / (ps * f)) - 1
        if ptper <= 0xFFF:
            break
    else:
        raise PwmError(f"inverter.pwm_frequency_hz = {f:g} Hz is below the slowest PCPWM period "
                       f"({FCY_HZ / (64 * 4096):.1f} Hz with prescaler 1:64): raise the PWM frequency")
    if ptper < 24:
        raise PwmError(f"inverter.pwm_frequency_hz = {f:g} Hz leaves PTPER = {ptper}: fewer than 100 duty "
                       "steps; lower the PWM frequency (at most 100 kHz gives 400 steps)")
    fa = FCY_HZ / (ps * (ptper + 1))
    return PwmPeriod(ptper=ptper, prescale=ps, ptckps=bits, frequency_hz=fa, requested_hz=f)


def dead_time(dead_time_ns: float) -> DeadTime:
    """DTCON for a dead time (ns): finest prescaler whose 6-bit count reaches it, rounded up."""
    d = float(dead_time_ns)
    if not (d >= 0 and math.isfinite(d)):
        raise PwmError(f"dead time {dead_time_ns!r} ns is not a number >= 0")
    for dtps, tosc in _DTPS_TOSC.items():
        tick_ns = tosc * 1e9 / FOSC_HZ
        dt = math.ceil(d / tick_ns - 1e-9)
        if dt <= 63:
            return DeadTime(dtcon=(dtps << 6) | dt, dtps=dtps, dt=dt, dead_time_ns=dt * tick_ns,
                            requested_ns=d)
    raise PwmError(f"inverter.dead_time_ns = {d:g} ns exceeds the longest dead time DTCON can insert "
                   f"({63 * 16 * 1e9 / FOSC_HZ:g} ns = 63 x 16 Tosc): lower the dead time")


def duty_limit(period: PwmPeriod, dt: DeadTime, bootstrap_refresh_ns: float,
               profile_max_duty: float | None = None) -> tuple[float, int]:
    """Largest duty (fraction, PDC counts) that keeps the IR2101 bootstrap charged.

    ``1 - (bootstrap_refresh_ns + 2 x dead time) / period`` with the achieved
    period and dead time (the formula of ``Profile.max_duty()``), not above
    ``profile_max_duty`` when given, rounded down to whole PDC counts.
    """
    md = 1.0 - (bootstrap_refresh_ns + 2.0 * dt.dead_time_ns) / period.period_ns
    if profile_max_duty is not None:
        md = min(md, profile_max_duty)
    if md < 0.5:
        raise PwmError(
            f"dead time x 2 ({2 * dt.dead_time_ns:g} ns achieved) plus bootstrap refresh "
            f"({bootstrap_refresh_ns:g} ns) leaves a duty limit of {md:.3f} of the {period.period_ns:.0f} ns "
            "PWM period (less than half): lower inverter.pwm_frequency_hz, inverter.dead_time_ns or "
            "inverter.bootstrap_refresh_ns")
    counts = int(math.floor(md * period.duty_full_counts + 1e-9))
    return counts / period.duty_full_counts, counts


# ---------------------------------------------------------------------------
# Commutation: the hall table (picdrive.commutation) with the override registers
# ---------------------------------------------------------------------------
def drive_state_registers(source: int, sink: int) -> tuple[int, int]:
    """(OVDCOND, OVDCONS) for high side of ``source`` modulated, low side of ``sink`` on."""
    return 1 << (2 * source + 1), 1 << (2 * sink)


def ident_vector_registers() -> tuple[tuple[int, int], ...]:
    """(OVDCONS, OVDCOND) of each identification vector (:data:`picdrive.commutation.IDENT_VECTORS`):
    the sources' high sides duty-driven, the sinks' low sides forced on."""
    out = []
    for sources, sinks in IDENT_VECTORS:
        cond = sum(drive_state_registers(s, sinks[0])[0] for s in sources)
        cons = sum(drive_state_registers(sources[0], k)[1] for k in sinks)
        out.append((cons, cond))
    return tuple(out)


@dataclass(frozen=True)
class CommutationTable:
    """Hall-code-indexed six-step table for both directions.

    ``forward[code]`` / ``reverse[code]``: ``(source, sink)`` phase indices or
    None for an invalid code.  ``ovdcond``/``ovdcons``: ``[direction][code]``
    register values (direction 0 forward, 1 reverse; 0/0 for invalid codes).
    """

    hall_spacing_deg: int
    hall_offset_deg: float
    forward: tuple
    reverse: tuple
    valid_mask: int
    sequence: tuple          # codes in forward order
    ovdcond: tuple = field(default=())
    ovdcons: tuple = field(default=())

    def describe(self, code: int, direction: int = 0) -> str:
        st = (self.forward if direction == 0 else self.reverse)[code]
        return "fault" if st is None else f"{PHASES[st[0]]}+{PHASES[st[1]]}-"


def commutation_table(hall_spacing_deg: int, hall_offset_deg: float,
                      back_emf_shape: str = "trapezoidal") -> CommutationTable:
    """The six-step table of :func:`picdrive.commutation.hall_table` (the drive state with the
    largest mean torque over each hall code's arc, both directions) with the OVDCOND/OVDCONS
    values of each state (:func:`drive_state_registers`)."""
    if hall_spacing_deg not in (60, 120):
        raise PwmError(f"sensors.hall_spacing_deg = {hall_spacing_deg!r}: expected 60 or 120")
    h = hall_table(hall_spacing_deg, hall_offset_deg, back_emf_shape)
    fwd, rev, valid, order = h.forward, h.reverse, h.valid_mask, h.sequence
    ovd = tuple(tuple(drive_state_registers(*st)[0] if st else 0 for st in tab) for tab in (fwd, rev))
    ovs = tuple(tuple(drive_state_registers(*st)[1] if st else 0 for st in tab) for tab in (fwd, rev))
    return CommutationTable(hall_spacing_deg=hall_spacing_deg, hall_offset_deg=float(hall_offset_deg),
                            forward=tuple(fwd), reverse=tuple(rev), valid_mask=valid,
                            sequence=tuple(order), ovdcond=ovd, ovdcons=ovs)


@dataclass(frozen=True)
class PwmPlan:
    period: PwmPeriod
    dead: DeadTime
    max_duty: float          # achieved duty limit (fraction)
    pdc_max: int             # PDC counts of the duty limit
    table: CommutationTable

    def lines(self) -> list[str]:
        p, d = self.period, self.dead
        return [
            f"PWM         edge-aligned, prescaler 1:{p.prescale}, PTPER = {p.ptper}: "
            f"{p.frequency_hz:.1f} Hz (asked {p.requested_hz:g} Hz), duty resolution "
            f"{p.duty_full_counts} counts ({p.duty_resolution_bits:.2f} bits)",
            f"dead time   DTCON = 0x{d.dtcon:02X} (DTPS = {d.dtps}, DT = {d.dt}): {d.dead_time_ns:g} ns "
            f"(asked {d.requested_ns:g} ns)",
            f"max duty    {self.max_duty:.4f} = {self.pdc_max}/{p.duty_full_counts} counts "
            "(2 x dead time + bootstrap refresh of low time per period)",
            "commutation " + ", ".join(f"{c:03b}:{self.table.describe(c)}" for c in self.table.sequence)
            + " (forward; invalid codes: "
            + ", ".join(f"{c:03b}" for c in range(8) if not self.table.valid_mask >> c & 1) + ")",
        ]


def plan_pwm(profile) -> PwmPlan:
    """Everything the PCPWM needs for a profile."""
    inv, se = profile.inverter, profile.sensors
    per = pwm_period(inv.pwm_frequency_hz)
    dt = dead_time(inv.dead_time_ns)
    md, counts = duty_limit(per, dt, inv.bootstrap_refresh_ns, profile.max_duty())
    tab = commutation_table(se.hall_spacing_deg, se.hall_offset_deg, profile.motor.back_emf_shape)
    return PwmPlan(period=per, dead=dt, max_duty=md, pdc_max=counts, table=tab)
