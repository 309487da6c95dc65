"""Six-step commutation: which phase pair the bridge drives for each hall code.

A fact of the motor and its sensors (the profile's ``sensors.hall_spacing_deg``,
``sensors.hall_offset_deg`` and ``motor.back_emf_shape``), used by the plant
models, the firmware's PWM override table (:mod:`picdrive.firmware.pcpwm`
adds the register bytes) and the twin.

Hall convention (the same as the twin's plant): electrical angle ``th``;
phase A back-EMF rises through zero at ``th = 0``; B and C lag by 120 and
240 degrees.  Hall k (k = 0, 1, 2 for A, B, C) reads 1 while ``(th -
hall_offset_deg - k x hall_spacing_deg) mod 360`` is in [0, 180).  The hall
code is ``(C << 2) | (B << 1) | A``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["PHASES", "DRIVE_STATES", "HallTable", "emf_unit", "hall_code_at", "hall_table", "IDENT_VECTORS",
           "IDENT_HALL_SELECTIONS", "ident_vector_angle_deg", "hall_positions", "ident_hall_vector"]

PHASES = "ABC"

#: the six drive states as (source, sink) phase indices: source high side modulated, sink low side on
DRIVE_STATES = [(s, k) for s in range(3) for k in range(3) if s != k]


def emf_unit(shape: str, th: np.ndarray) -> np.ndarray:
    """Per-unit back-EMF of phase A at electrical angle ``th`` (rad): rising zero at 0; the
    trapezoid is flat over [30, 150] deg (the twin's convention too)."""
    if shape == "sinusoidal":
        return np.sin(th)
    t = np.mod(th + math.pi / 6, 2 * math.pi)
    p3 = math.pi / 3
    return np.select([t < p3, t < math.pi, t < math.pi + p3],
                     [(t - math.pi / 6) / (math.pi / 6), 1.0, 1.0 - (t - math.pi) / (math.pi / 6)], -1.0)


def hall_code_at(theta_e_deg, hall_spacing_deg: int, hall_offset_deg: float):
    """Hall code (``C<<2 | B<<1 | A``) at electrical angle(s) ``theta_e_deg`` (deg)."""
    th = np.asarray(theta_e_deg, dtype=float)
    code = np.zeros(th.shape, dtype=int)
    for k in range(3):
        x = np.mod(th - hall_offset_deg - k * hall_spacing_deg, 360.0)
        code |= (x < 180.0).astype(int) << k
    return code


@dataclass(frozen=True)
class HallTable:
    """Hall-code-indexed six-step table for both directions.

    ``forward[code]`` / ``reverse[code]``: ``(source, sink)`` phase indices, or
    None for a code that never occurs (a fault); ``sequence``: the codes in
    forward order; ``valid_mask``: bit ``code`` set for every valid code.
    """

    hall_spacing_deg: int
    hall_offset_deg: float
    forward: tuple
    reverse: tuple
    valid_mask: int
    sequence: tuple

    def describe(self, code: int, direction: int = 0) -> str:
        st = (self.forward if direction == 0 else self.reverse)[code]
        return "fault" if st is None else f"{PHASES[st[0]]}+{PHASES[st[1]]}-"


def hall_table(hall_spacing_deg: int, hall_offset_deg: float, back_emf_shape: str = "trapezoidal") -> HallTable:
    """Six-step table from the hall placement.

    For each hall code, the drive state (source phase high side, sink phase
    low side) with the largest mean torque over the electrical arc where the
    code is seen (forward), or the most negative (reverse).  A tie (the hall
    edges fall exactly between two commutation points, e.g. ``hall_offset_deg
    = 0``) is broken towards phase advance in the direction of rotation.
    Codes that never occur are faults: 000 and 111 for 120-degree halls, 010
    and 101 for 60-degree halls (a 60-degree set is a 120-degree set with hall
    B inverted and B, C swapped; the arc method maps it directly).
    """
    if hall_spacing_deg not in (60, 120):
        raise ValueError(f"sensors.hall_spacing_deg = {hall_spacing_deg!r}: expected 60 or 120")
    n = 7200
    th_deg = (np.arange(n) + 0.5) * (360.0 / n)
    codes = hall_code_at(th_deg, hall_spacing_deg, hall_offset_deg)
    th = np.radians(th_deg)
    f = [emf_unit(back_emf_shape, th - k * 2 * math.pi / 3) for k in range(3)]
    torque = {st: f[st[0]] - f[st[1]] for st in DRIVE_STATES}
    fwd, rev = [None] * 8, [None] * 8
    valid = 0
    for code in range(8):
        sel = codes == code
        if not sel.any():
            continue
        valid |= 1 << code
        ang = th[sel]
        # circular mean angle of the arc, for the tie-break
        centre = math.atan2(np.sin(ang).mean(), np.cos(ang).mean())
        for direction, out in ((1, fwd), (-1, rev)):
            best, best_key = None, None
            for st in DRIVE_STATES:
                mean_t = direction * float(torque[st][sel].mean())
                # where is this state at its best (largest direction*torque)?
                peak = th[np.argmax(direction * torque[st])]
                lead = math.remainder(peak - centre, 2 * math.pi) * direction  # > 0: advanced
                key = (round(mean_t, 9), lead)
                if best_key is None or key > best_key:
                    best, best_key = st, key
            out[code] = best
    # forward sequence of codes
    order, seen = [], set()
    for c in codes:
        if not order or order[-1] != c:
            if int(c) in seen:
                break
            order.append(int(c))
            seen.add(int(c))
    return HallTable(hall_spacing_deg=hall_spacing_deg, hall_offset_deg=float(hall_offset_deg),
                     forward=tuple(fwd), reverse=tuple(rev), valid_mask=valid, sequence=tuple(order))


# ---------------------------------------------------------------------------
# Identification vectors: the stator current directions the bridge can apply
# ---------------------------------------------------------------------------
#: The twelve identification vectors, index ``m`` = 0..11, as ``(sources, sinks)`` phase-index
#: tuples: the sources' high sides modulated (all at one duty), the sinks' low sides on.  Even
#: ``m`` is the two-phase drive state ``m / 2`` of the forward six-step order (A+B-, A+C-, B+C-,
#: B+A-, C+A-, C+B-), odd ``m`` the three-phase state between its neighbours.  The current
#: vector of ``m`` points at ``ident_vector_angle_deg(m)`` = -30 + 30 m electrical degrees
#: (phase A's axis at 0, B at 120, C at 240).
IDENT_VECTORS: tuple[tuple[tuple[int, ...], tuple[int, ...]], ...] = (
    ((0,), (1,)), ((0,), (1, 2)), ((0,), (2,)), ((0, 1), (2,)), ((1,), (2,)), ((1,), (0, 2)),
    ((1,), (0,)), ((1, 2), (0,)), ((2,), (0,)), ((2,), (0, 1)), ((2,), (1,)), ((0, 2), (1,)),
)

#: hall-driven selections: ``sel`` = 0..11 applies, at hall code ``c``, the two-phase vector
#: ``2 ((s pos(c) + shift) mod 6)`` with ``s = +1`` for sel < 6, ``-1`` above, ``shift = sel mod 6``
#: and ``pos(c)`` the code's place in the build's forward hall sequence (hall_spacing_deg, offset 0).
IDENT_HALL_SELECTIONS = 12


def ident_vector_angle_deg(m: int) -> float:
    """Electrical angle (deg) of identification vector ``m``'s current: -30 + 30 m.

    A rotor held by this current settles where its magnet's axis points along it, at the
    electrical angle (the back-EMF convention above) ``ident_vector_angle_deg(m) + 180``:
    the torque of a current at angle ``phi`` on a rotor at ``th`` is proportional to
    ``sin(th - phi)``, zero with a negative slope at ``th = phi + 180``."""
    return -30.0 + 30.0 * (int(m) % 12)


def hall_positions(hall_spacing_deg: int) -> dict[int, int]:
    """Each valid hall code's place 0..5 in the forward sequence at hall offset 0."""
    seq = hall_table(hall_spacing_deg, 0.0).sequence
    start = seq.index(min(seq))
    seq = seq[start:] + seq[:start]
    return {c: i for i, c in enumerate(seq)}


def ident_hall_vector(sel: int, code: int, hall_spacing_deg: int) -> int | None:
    """The identification vector (even ``m``) hall-driven selection ``sel`` applies at ``code``,
    or None for a code outside the build's hall sequence (outputs off)."""
    pos = hall_positions(hall_spacing_deg)
    if code not in pos:
        return None
    s = 1 if sel < 6 else -1
    return 2 * ((s * pos[code] + sel % 6) % 6)
