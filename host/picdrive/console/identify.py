"""``picdrive identify``: measure the motor on the board and write the profile it makes.

The board's firmware (any build of the normal firmware: the identification mode is the
``ident`` command, state IDENT) applies the current vectors; this module drives the
procedure over the link and hands the data to :mod:`picdrive.analysis.identify`:

1. first current (open or shorted winding), then the rotor held at the twelve vectors: the hall
   code at each (hall table and offset), the encoder position (lines, direction);
2. locked-rotor currents at three duties (R line-to-line, the freewheel drop) and a current step
   sampled by the board's capture (L line-to-line);
3. hall-driven steady spins: two selections at one duty (the hall offset from their speed
   ratio, :func:`picdrive.analysis.identify.commutation_factor`), then a second duty (Kb = Kt,
   viscous and Coulomb friction), the acceleration between them and a coast-down (J).

Currents stay at or under 60 % of the smaller of the profile's ``inverter.current_limit_a`` and
``motor.rated_current_a`` (the board's ``current_limit`` parameter is lowered to that smaller
value for the run: the firmware faults above it), speeds under 80 % of
``control.speed_max_rpm``.  Any fault, refusal or Ctrl-C stops the motor (outputs off) first.
"""
from __future__ import annotations

import math
import time
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from ..analysis import identify as fit
from ..analysis.identify import Measured
from ..errors import PicdriveError

__all__ = ["IdentifyError", "Identification", "identify", "profile_text", "register"]

RPM = 30.0 / math.pi          # rpm per rad/s


class IdentifyError(PicdriveError):
    """The measurement was refused or stopped: what was seen, and the fix."""


@dataclass
class Identification:
    """What was measured (name -> :class:`Measured`), the hall sweep, and notes."""
    values: dict[str, Measured] = field(default_factory=dict)
    hall_codes: tuple[int, ...] = ()
    hall_table: object = None
    notes: list[str] = field(default_factory=list)
    complete: bool = False


class _Board:
    """The link calls the procedure makes, with its limits."""

    def __init__(self, link, profile, progress: Callable[[str], None]):
        from ..firmware.pcpwm import plan_pwm
        self.link = link
        self.profile = profile
        self.say = progress
        pwm = plan_pwm(profile)
        self.full = pwm.period.duty_full_counts
        self.pdc_max = pwm.pdc_max
        self.vbus = profile.inverter.bus_voltage_v
        self.i_max = min(profile.inverter.current_limit_a, profile.motor.rated_current_a)
        self.lsb = link.param("current").scale
        self.loop_hz = profile.control.speed_loop_hz
        self.has_encoder = profile.sensors.has_encoder
        self.lines_fw = profile.sensors.encoder_lines
        self.speed_scale = 1.0          # true / reported speed (the encoder's lines as measured)

    # -- commands -----------------------------------------------------------
    def ident(self, vector: int, duty: float, step_ms: int = 0) -> None:
        from ..link.client import NackError
        from ..link.protocol import Nack
        pdc = int(round(min(max(duty, 0.0), self.pdc_max / self.full) * self.full))
        try:
            self.link.request("ident", {"vector": int(vector), "duty": pdc, "step_ms": int(step_ms)})
        except NackError as e:
            if e.code == Nack.UNKNOWN_COMMAND:      # a build that does not say in hello (protocol 2.0)
                raise IdentifyError(NO_IDENT_COMMAND) from None
            self.check(f"vector {vector}")          # a latched fault, named
            raise

    def off(self) -> None:
        self.link.stop()

    def check(self, what: str) -> None:
        """A latched fault ends the run, named."""
        st = self.link.status()
        if int(st.fault) != 0:
            raise IdentifyError(_fault_text(st.fault, what))

    def read(self, *names: str) -> dict:
        return self.link.get_many(*names)

    def mean(self, name: str, n: int, dt: float = 0.004) -> tuple[float, float]:
        xs = []
        for _ in range(n):
            xs.append(float(self.link.get(name)))
            time.sleep(dt)
        a = np.array(xs)
        return float(a.mean()), float(a.std() / math.sqrt(len(a)))

    def speed_rad_s(self, rpm) -> np.ndarray:
        return np.asarray(rpm, float) / RPM * self.speed_scale


def _fault_text(code, what: str) -> str:
    from ..link.protocol import Fault
    name = Fault(int(code)).name if int(code) in {int(f) for f in Fault} else str(code)
    why = {
        "HALL_INVALID": "the board read hall code 000 or 111, which a 120-degree hall set never gives: "
                        "a hall line open or shorted, or the sensors unpowered; check the hall wiring",
        "OVERCURRENT": "the current passed the limit: a shorted winding or phase-to-phase short, or a "
                       "resistance far below the profile's; check the motor leads",
        "UNDERVOLTAGE": "the bus sagged under its limit: a supply too weak for the test current",
        "OVERVOLTAGE": "the bus rose over its limit (energy returned while the motor slowed)",
        "LINK_LOST": "the board's link watchdog expired (no command in time)",
        "OVERSPEED": "the speed passed the overspeed trip",
        "STALL": "the motor stalled",
    }.get(name, "")
    return f"{what}: the board latched fault {name.lower()}" + (f" ({why})" if why else "") + "; outputs are off"


def _settle_lock(b: _Board, timeout_s: float = 2.0) -> tuple[int, int]:
    """Wait until the held rotor stops (position and hall unchanged over 4 reads); (hall, position)."""
    t0 = time.monotonic()
    last, same = None, 0
    time.sleep(0.06)
    while True:
        v = b.read("hall", "position")
        cur = (int(v["hall"]), int(v["position"]) & 0xFFFF)
        same = same + 1 if cur == last else 0
        last = cur
        if same >= 4 or time.monotonic() - t0 > timeout_s:
            return cur
        time.sleep(0.025)


def _steady(b: _Board, timeout_s: float) -> float:
    """Wait until the speed holds within 0.3 % over six reads 100 ms apart while the winding
    conducts (a coasting rotor, faster than the duty holds, is not steady); the speed (rpm)."""
    t0 = time.monotonic()
    hist = []
    while True:
        time.sleep(0.1)
        v = b.read("speed", "current")
        hist.append(float(v["speed"]))
        if len(hist) >= 6 and float(v["current"]) > 1.5 * b.lsb:
            w = hist[-6:]
            if max(w) - min(w) <= 0.003 * max(abs(np.mean(w)), 1.0):
                return hist[-1]
        if time.monotonic() - t0 > timeout_s:
            return hist[-1]


def _record(b: _Board, seconds: float) -> np.ndarray:
    """Telemetry of speed and current for ``seconds`` (host time)."""
    b.link.configure_telemetry(["speed", "current"], decimation=1)
    try:
        return b.link.read_samples(seconds=seconds)
    finally:
        b.link.stop_telemetry()


_FLASH_IDENT = ("Generate the identification build with 'picdrive firmware --identify --profile P --design D', "
                "flash it, run 'picdrive identify' again, then flash the drive firmware (built without "
                "--identify) back")
NO_IDENT_MODE = ("the board's firmware has no identification mode (hello: no ident feature); nothing was "
                 "commanded. " + _FLASH_IDENT)
NO_IDENT_COMMAND = ("the board's firmware has no identification mode (it answered ident UNKNOWN_COMMAND; the "
                    "outputs stayed off). " + _FLASH_IDENT)


def identify(link, profile, *, progress: Callable[[str], None] = print) -> Identification:
    """Run the measurement on a connected board (handshake done).  Raises :class:`IdentifyError`
    on a refusal or fault; the :class:`Identification` passed in ``exc.partial`` holds what was
    measured before it.  The motor is stopped on every exit.  A build without the identification
    mode (hello's features) is refused before any command."""
    info = getattr(link, "info", None)
    if info is not None and info.has_ident is False:
        raise IdentifyError(NO_IDENT_MODE)
    res = Identification()
    b = _Board(link, profile, progress)
    old_limit = None
    try:
        st = link.status()
        if int(st.fault) != 0:
            raise IdentifyError(_fault_text(st.fault, "before the start") + ": clear it (picdrive console, "
                                "'clear') and check why it latched")
        if int(st.state) != 0:
            raise IdentifyError(f"the board is in state {st.state.name.lower()}: stop the motor first")
        old_limit = float(link.get("current_limit"))
        link.set("current_limit", min(old_limit, b.i_max))
        link.start_keepalive()
        _first_current(b, res)
        _hall_sweep(b, res)
        _resistance(b, res)
        _inductance(b, res)
        _spins(b, res)
        res.complete = True
        return res
    except IdentifyError as e:
        e.partial = res
        raise
    except PicdriveError as e:                 # the link: a timeout, a refused command
        err = IdentifyError(f"the board stopped answering as expected: {e}; the motor was told to stop")
        err.partial = res
        raise err from None
    except KeyboardInterrupt:
        res.notes.append("interrupted (Ctrl-C): the motor was stopped")
        raise
    finally:
        try:
            b.off()
            if old_limit is not None:
                link.set("current_limit", old_limit)
        except Exception:                      # noqa: BLE001 - the link may be gone; outputs are off then
            pass


# ---------------------------------------------------------------------------
def _first_current(b: _Board, res: Identification) -> None:
    """A first locked-rotor current at a duty safe for a resistance down to 0.4 x the profile's."""
    m = b.profile.motor
    r_guess = 0.4 * m.r_line_ohm
    target = 0.3 * b.i_max
    duty = max(target * r_guess / b.vbus, 2.0 / b.full)
    b.say(f"first current: vector 0 at duty {duty:.4f} ({duty * b.vbus:.2f} V), expecting <= {target:.3g} A")
    for _ in range(6):
        b.ident(0, duty)
        time.sleep(0.05 + 10 * m.l_line_h / m.r_line_ohm)
        b.check("first current")
        i, _ = b.mean("current", 5)
        if i >= 4 * b.lsb:
            break
        duty *= 2.0
        if duty * b.vbus / max(b.i_max, 1e-9) > 20 * m.r_line_ohm or duty >= b.pdc_max / b.full:
            b.off()
            raise IdentifyError(f"open winding: no current ({i:.3g} A) at {duty * b.vbus / 2:.2f} V across phases "
                                f"A and B (the profile's {m.r_line_ohm:g} ohm would draw "
                                f"{duty * b.vbus / 2 / m.r_line_ohm:.3g} A); check the motor leads and connector")
    r0 = duty * b.vbus / i
    if r0 < 0.2 * m.r_line_ohm:
        b.off()
        raise IdentifyError(f"shorted winding: {i:.3g} A at {duty * b.vbus:.2f} V is {r0:.3g} ohm line-to-line, under "
                            f"a fifth of the profile's {m.r_line_ohm:g} ohm; check the motor leads for a short")
    b.r0 = r0
    b.align_duty = min(0.5 * b.i_max * r0 / b.vbus, b.pdc_max / b.full)
    b.say(f"  {i:.3g} A: about {r0:.3g} ohm line-to-line; holding the rotor at {0.5 * b.i_max:.3g} A")


def _hall_sweep(b: _Board, res: Identification) -> None:
    se, m = b.profile.sensors, b.profile.motor
    b.say("hall sweep: the rotor held at 12 vectors, 30 electrical degrees apart")
    codes, pos = [], []
    for k in range(13):
        # a third of the holding current first: the rotor moves to the new lock gently (a snap at full
        # current can pass the overspeed trip of a hall-speed build), then the full current holds it
        b.ident(k % 12, b.align_duty / 3.0)
        time.sleep(0.06)
        b.ident(k % 12, b.align_duty)
        code, p = _settle_lock(b)
        b.check(f"hall sweep, vector {k % 12}")
        if k < 12:
            codes.append(code)
        pos.append(p)
        b.say(f"  vector {k % 12:2d} ({fit.lock_angle_deg(k % 12):5.1f} deg): hall {code:03b}, position {p}")
    res.hall_codes = tuple(codes)
    if len(set(codes)) == 1:
        raise IdentifyError(f"the motor does not turn: the hall code stayed {codes[0]:03b} while the field turned a "
                            "full electrical turn at " f"{0.5 * b.i_max:.3g} A (a stalled or locked rotor, a brake "
                            "engaged, or the halls not connected)")
    bad = [c for c in codes if (se.hall_spacing_deg == 120 and c in (0, 7))]
    if bad:
        raise IdentifyError(f"hall code {bad[0]:03b} seen with the rotor held: a 120-degree hall set never gives "
                            "000 or 111; a hall line is open or shorted, or the sensors are unpowered")
    if b.has_encoder:
        # the firmware's counter resets at 4 x the lines it was built for (QEI with MAXCNT reset)
        enc = fit.fit_encoder(pos, m.pole_pairs, modulus=4 * b.lines_fw if b.lines_fw else 65536)
        cpt = enc["counts_per_turn"]
        if cpt == 0:
            raise IdentifyError("the encoder does not count: the position stayed "
                                f"{pos[0]} while the halls saw the rotor turn (check the encoder's supply and A/B lines)")
        if cpt < 0:
            raise IdentifyError(f"the encoder counts the wrong way: {cpt} counts over a forward electrical turn "
                                "(swap its A and B lines)")
        lines = enc["lines"]
        # the lock angles scatter by a few counts (a rotor creeping to its lock): a count within three
        # standard deviations of the profile's is the profile's, confirmed; else the nearest whole one
        sig = max(lines.sigma, 0.5)
        if se.encoder_lines and abs(lines.value - se.encoder_lines) <= 3.0 * sig:
            res.values["encoder_lines"] = Measured(float(se.encoder_lines), sig, lines.how + f": {lines.value:.1f}, "
                                                   f"the profile's {se.encoder_lines} within 3 sigma")
        else:
            res.values["encoder_lines"] = Measured(float(round(lines.value)), sig, lines.how)
        if abs(lines.value - round(lines.value)) > 0.25 * max(lines.value / 100.0, 1.0):
            res.notes.append(f"encoder: {lines.value:.2f} lines is not a whole number (pole_pairs "
                             f"{m.pole_pairs} from the profile may be wrong)")
        if se.encoder_lines and res.values["encoder_lines"].value != se.encoder_lines:
            b.speed_scale = se.encoder_lines / res.values["encoder_lines"].value
        b.say(f"  encoder: {cpt} counts per electrical turn -> {lines.value:.1f} lines")
    hf = fit.fit_halls(codes, se.hall_spacing_deg)
    if hf is None:
        raise IdentifyError("the hall sensors are wired in the other order relative to the motor phases: no hall "
                            f"offset in picdrive's convention gives the codes seen ({' '.join(f'{c:03b}' for c in codes)} "
                            "at vectors 0..11); swap two motor phase leads (or two hall lines) and run identify again")
    b.hall = hf
    b.say(f"  hall codes consistent with offsets {hf.interval[0]:.1f} .. {hf.interval[1]:.1f} deg")


def _resistance(b: _Board, res: Identification) -> None:
    m = b.profile.motor
    b.say("resistance: locked rotor at three currents")
    duties, cur = [], []
    for frac in (0.2, 0.4, 0.6):
        d = frac * b.i_max * b.r0 / b.vbus
        b.ident(0, d)
        time.sleep(0.05 + 10 * m.l_line_h / m.r_line_ohm)
        b.check("resistance")
        i, _ = b.mean("current", 12)
        pdc = int(round(d * b.full))
        duties.append(pdc / b.full)
        cur.append(i)
        b.say(f"  duty {pdc / b.full:.4f}: {i:.4g} A")
    r, vd = fit.fit_resistance(duties, cur, b.vbus, b.lsb)
    res.values["resistance_line_ohm"] = r
    res.values["freewheel_drop_v"] = vd
    b.r = r
    b.vd = vd.value
    b.say(f"  R = {r.value:.4g} +- {r.sigma:.2g} ohm line-to-line, freewheel drop {vd.value:.3g} V")


def _inductance(b: _Board, res: Identification) -> None:
    b.say("inductance: locked-rotor current step, captured at the speed-loop rate")
    b.off()
    time.sleep(0.03)
    d = 0.5 * b.i_max * b.r.value / b.vbus
    link = b.link
    n = min(64, int(link.info.capture_words)) if getattr(link, "info", None) else 64
    link.capture_arm(["current"], n)
    b.ident(0, d)
    cap = link.capture_read(timeout=5.0)
    b.check("inductance")
    b.off()                                  # outputs off while the host computes
    t = cap.data["t"]
    i = cap.data["current"]
    i_final = float(np.mean(i[-max(4, n // 4):]))
    tau = fit.fit_time_constant(t, i, i_final, b.lsb)
    if tau is None:
        res.notes.append(f"inductance not measured: L/R is under what the {b.loop_hz:g} Hz capture resolves "
                         "(about 0.5 ms); the profile's inductance is kept")
        b.say("  L/R too short for the capture: the profile's inductance kept")
        return
    L = tau.value * b.r.value
    b.tau = tau.value
    sl = L * math.hypot(tau.rel, b.r.rel)
    res.values["inductance_line_h"] = Measured(L, sl, tau.how + f"; L = tau R (tau = {tau.value * 1e3:.3f} ms)")
    b.say(f"  tau = {tau.value * 1e3:.3f} ms, L = {L * 1e3:.4g} mH line-to-line")


def _spin_to(b: _Board, sel: int, duty: float, rpm: float, limit_rpm: float, timeout_s: float) -> tuple[float, float]:
    """Ramp the hall-driven selection until the speed reaches ``rpm`` or the duty ``duty`` (the
    current under 60 % of the limit, the speed under ``limit_rpm``), then wait for a steady speed;
    (duty reached, speed rpm)."""
    cur_d = getattr(b, "spin_duty", 0.0)
    step = max(0.1 * b.i_max * b.r.value / b.vbus, 1.0 / b.full)
    t0 = time.monotonic()
    above = 0
    while True:
        v = b.read("speed", "current")
        sp = abs(float(v["speed"])) * b.speed_scale
        # two reads in a row at the target (one can be the speed estimator's last value from before)
        above = above + 1 if (cur_d > 0 and sp >= min(rpm, limit_rpm)) else 0
        if above >= 2 or cur_d >= duty or time.monotonic() - t0 > timeout_s:
            break
        if float(v["current"]) > 0.6 * b.i_max:
            time.sleep(0.03)
            continue
        # near the target speed, smaller steps
        frac = 0.25 if sp > 0.7 * rpm else 1.0
        cur_d = min(duty, cur_d + frac * step)
        b.ident(12 + sel, cur_d)
        time.sleep(0.03)
        b.check("spin")
    b.spin_duty = cur_d
    s = _steady(b, timeout_s)
    b.check("spin")
    return cur_d, s


def _point(b: _Board, seconds: float = 0.6) -> tuple[float, float, float]:
    """Mean current (A), its standard error and mean speed (rad/s) over ``seconds`` of telemetry."""
    d = _record(b, seconds)
    if len(d) < 20:
        i, si = b.mean("current", 60)
        s, _ = b.mean("speed", 30)
        return i, si, float(b.speed_rad_s(s))
    i = np.asarray(d["current"], float)
    # the samples are correlated over a hall sector: the standard error from 10 blocks
    blocks = np.array_split(i, 10)
    si = float(np.std([x.mean() for x in blocks]) / math.sqrt(len(blocks)))
    return float(i.mean()), si, float(b.speed_rad_s(np.mean(d["speed"])))


def _spins(b: _Board, res: Identification) -> None:
    prof = b.profile
    se, m = prof.sensors, prof.motor
    hf = b.hall
    spacing = se.hall_spacing_deg
    lo, hi = hf.interval
    offs = np.arange(lo, hi + 1e-9, 0.5)

    cache: dict = {}

    def g(sel, o):
        key = (sel, round(float(o), 6))
        if key not in cache:
            cache[key] = fit.commutation_factor(sel, spacing, o, m.back_emf_shape)
        return cache[key]
    # the selection best over the whole interval, and its neighbour that says most about the offset
    sel_a = max(range(12), key=lambda s: min(g(s, o) for o in (lo, 0.5 * (lo + hi), hi)))
    nb = [(sel_a // 6) * 6 + (sel_a % 6 + k) % 6 for k in (1, 5)]
    sel_b = max(nb, key=lambda s: g(s, 0.5 * (lo + hi)))
    # the ratio the offset is read from, computed before the motor turns: no long computation while
    # it spins (the link's keep-alive stops when the program stops calling it)
    gr = np.array([g(sel_b, o) / g(sel_a, o) for o in offs])
    limit_rpm = 0.8 * prof.control.speed_max_rpm
    tau_m = m.inertia_kg_m2 * m.r_line_ohm / max(m.kt_n_m_per_a ** 2, 1e-12)
    timeout = min(max(3.0, 16 * tau_m), 12.0)
    d_top = 0.85 * b.pdc_max / b.full
    # low speed first: a hall sector of at least 8 L/R, so that the winding's lag does not shift the
    # commutation the offset and Kb are read from
    tau_e = b.tau if getattr(b, "tau", None) else m.l_line_h / m.r_line_ohm
    rpm_a = min(max(60.0 / (m.pole_pairs * 6 * 8 * tau_e), 0.05 * limit_rpm), 0.2 * limit_rpm)
    b.say(f"spins: hall-driven selections {sel_a} and {sel_b} at about {rpm_a:.0f} rpm (the offset from their "
          "speed ratio)")
    # from the held vector to a hall-driven one through one off period: no leg goes from its high
    # side to its low side directly (the spins' own changes are between neighbouring vectors)
    b.off()
    time.sleep(0.01)
    b.spin_duty = 0.0
    t_end = time.monotonic() + 1.0          # the speed estimate back at rest after the sweep's moves
    while time.monotonic() < t_end and abs(float(b.read("speed")["speed"])) > 0.01 * limit_rpm:
        time.sleep(0.05)
    d1, _ = _spin_to(b, sel_a, d_top, rpm_a, limit_rpm, timeout)
    i_a, si_a, w_a = _point(b)
    b.ident(12 + sel_b, d1)
    _steady(b, timeout)
    b.check("spin")
    i_b, si_b, w_b = _point(b)
    v1 = d1 * (b.vbus + b.vd) - b.vd
    if abs(w_a) < 1.0 or abs(w_b) < 1.0:
        raise IdentifyError(f"the motor does not spin under hall-driven commutation ({w_a * RPM:.0f} / "
                            f"{w_b * RPM:.0f} rpm at duty {d1:.3f}): a stalled rotor or a load too large for the "
                            "test current")
    ratio = ((v1 - b.r.value * i_b) / w_b) / ((v1 - b.r.value * i_a) / w_a)
    k = int(np.argmin(np.abs(gr - ratio)))
    o_est = float(offs[k])
    slope = float(np.gradient(gr, offs)[k]) if len(offs) > 2 else 0.0
    s_ratio = abs(ratio) * math.hypot(b.r.value * math.hypot(si_a, si_b) / max(v1 - b.r.value * i_a, 1e-9), 3e-3)
    s_o = min(abs(s_ratio / slope), 0.5 * (hi - lo)) if slope else 0.5 * (hi - lo)
    snap = 30.0 * round(o_est / 30.0)
    snapped = abs(o_est - snap) <= max(2.0 * s_o, 3.0) and lo - 3.0 <= snap <= hi + 3.0
    o_fin = snap if snapped else o_est
    o_fin = (o_fin + 180.0) % 360.0 - 180.0
    how = (f"hall codes at 12 locked vectors (offsets {lo:.1f} .. {hi:.1f} deg fit), then the speed ratio of "
           f"hall-driven selections {sel_a}/{sel_b} at one duty: {o_est:.1f} deg"
           + (f", taken as {o_fin:g} (the multiple of 30 within its uncertainty)" if snapped else ""))
    res.values["hall_offset_deg"] = Measured(o_fin, s_o, how)
    from ..commutation import hall_table
    res.hall_table = hall_table(spacing, o_fin, m.back_emf_shape)
    ga = g(sel_a, o_fin)
    b.say(f"  {w_a * RPM:.0f} / {w_b * RPM:.0f} rpm: hall offset {o_est:.1f} deg -> {o_fin:g} deg; "
          f"commutation factor {ga:.4f}")
    # Kb from three low speeds (the first spin's, then 2 and 3 x faster: each approached from below, as
    # the other selection may have spun the rotor faster), friction from those and a high one, J from
    # the acceleration to it and the coast-down from it
    pts = [(d1, i_a, si_a, w_a)]
    fastest = max(abs(w_a), abs(w_b)) * RPM
    for mult in (2.0, 3.0):
        d, _ = _spin_to(b, sel_a, d_top, max(mult * rpm_a, 1.25 * fastest), limit_rpm, timeout)
        pts.append((d,) + _point(b))
        fastest = max(fastest, abs(pts[-1][3]) * RPM)
    for d, i, si, w in pts:
        b.say(f"  duty {d:.3f}: {w * RPM:.0f} rpm, {i:.4g} A")
    volts = [d * (b.vbus + b.vd) - b.vd for d, *_ in pts]
    ks = [(v - b.r.value * p[1]) / (ga * p[3]) for v, p in zip(volts, pts)]
    if min(ks) <= 0 or (max(ks) - min(ks)) > 0.1 * abs(float(np.mean(ks))):
        raise IdentifyError("the steady spins disagree (back-EMF constant " + ", ".join(f"{k:.4g}" for k in ks)
                            + " V s/rad at " + ", ".join(f"{p[3] * RPM:.0f}" for p in pts) + " rpm): the speed did "
                            "not settle or the load changed; run identify again with the rotor free")
    kb = fit.fit_back_emf(volts, [p[1] for p in pts], [p[3] for p in pts], b.r, ga)
    # at light load the winding current may fall to zero within each PWM period (discontinuous
    # conduction): the winding then sees more than d Vbus on average and Kb reads low
    l_chk = res.values["inductance_line_h"].value if "inductance_line_h" in res.values else m.l_line_h
    t_pwm = 1.0 / prof.inverter.pwm_frequency_hz
    dcm = [p for p, v in zip(pts, volts)
           if p[1] < 0.5 * (b.vbus - v) * p[0] * t_pwm / max(l_chk, 1e-12)]
    if dcm:
        res.notes.append(f"the spins at {', '.join(f'{p[3] * RPM:.0f}' for p in dcm)} rpm drew less current than half "
                         "the PWM ripple (discontinuous conduction with L = "
                         f"{l_chk * 1e3:.3g} mH): the back-EMF constant may read low by several %")
    res.values["back_emf_constant_v_s"] = kb
    res.values["torque_constant_n_m_per_a"] = Measured(kb.value, kb.sigma, "= Kb (SI units, six-step DC equivalent)")
    b.say(f"  Kb = Kt = {kb.value:.5g} +- {kb.sigma:.2g} V s/rad")
    b.link.configure_telemetry(["speed", "current"], decimation=1)
    d3, _ = _spin_to(b, sel_a, d_top, limit_rpm, limit_rpm, timeout)
    acc = b.link.read_samples(seconds=0.0)
    b.link.stop_telemetry()
    pts.append((d3,) + _point(b))
    b.say(f"  duty {d3:.3f}: {pts[-1][3] * RPM:.0f} rpm, {pts[-1][1]:.4g} A")
    ws = [p[3] for p in pts]
    if max(ws) - min(ws) < 0.2 * max(ws):
        raise IdentifyError(f"the speed hardly changed between duties {d1:.3f} and {d3:.3f} "
                            f"({min(ws) * RPM:.0f} .. {max(ws) * RPM:.0f} rpm): the rotor is loaded or stalled")
    l_h = res.values["inductance_line_h"].value if "inductance_line_h" in res.values else m.l_line_h

    def kt_at(d, w):        # torque per mean ampere of the spin (the current's shape under this commutation)
        v = d * (b.vbus + b.vd) - b.vd
        return kb.value * fit.torque_factor(v, b.r.value, l_h, kb.value, w, sel_a, spacing, o_fin, m.back_emf_shape,
                                            m.pole_pairs)
    kts = [kt_at(p[0], p[3]) for p in pts]
    sig_t = max(kts) * (max(p[2] for p in pts) + b.lsb / math.sqrt(12.0))
    bv, tc = fit.fit_friction([k * p[1] for k, p in zip(kts, pts)], ws, sig_t)
    res.values["viscous_friction_n_m_s"] = bv
    res.values["coulomb_friction_n_m"] = tc
    b.say(f"  friction: B = {bv.value:.4g} N m s/rad, Tc = {tc.value:.4g} N m (torque per ampere "
          f"{min(kts):.4g} .. {max(kts):.4g} N m/A)")
    kt = float(np.interp(0.5 * (pts[-2][3] + pts[-1][3]), ws, kts))
    # coast-down from the top speed
    b.link.configure_telemetry(["speed", "current"], decimation=1)
    b.off()
    t_coast = min(max(1.0, 0.7 * m.inertia_kg_m2 / max(m.viscous_friction_n_m_s, 1e-12)), 3.0)
    t_end = time.monotonic() + t_coast
    while time.monotonic() < t_end:        # the link stays in use: the client's keep-alive holds
        time.sleep(0.2)
        b.read("state")
    coast = b.link.read_samples(seconds=0.0)
    b.link.stop_telemetry()
    cf = fit.fit_coast(coast["t"], b.speed_rad_s(coast["speed"]), bv) if coast is not None else None
    if cf is not None:
        res.values["inertia_kg_m2"], res.values["coulomb_friction_n_m"] = cf
        b.say(f"  J from the coast-down fit: {cf[0].value:.4g} +- {cf[0].sigma:.2g} kg m^2, Tc {cf[1].value:.3g} N m")
        return
    js = []
    for name, data, torque in (("acceleration", acc, True), ("coast-down", coast, False)):
        if data is None or len(data) < 10:
            continue
        w = b.speed_rad_s(data["speed"])
        tq = kt * np.asarray(data["current"], float) if torque else None
        j = fit.inertia_from_transient(data["t"], w, tq, bv.value, tc.value)
        if j is not None:
            js.append((name, j))
            b.say(f"  J from the {name}: {j.value:.4g} +- {j.sigma:.2g} kg m^2")
    if not js:
        res.notes.append("inertia not measured: the speed transients were too small; the profile's inertia is kept")
        return
    wts = np.array([1.0 / max(j.sigma, 1e-30) ** 2 for _, j in js])
    jv = float(sum(wt * j.value for wt, (_, j) in zip(wts, js)) / wts.sum())
    js_ = float(1.0 / math.sqrt(wts.sum()))
    spread = float(np.ptp([j.value for _, j in js])) / 2 if len(js) > 1 else 0.0
    res.values["inertia_kg_m2"] = Measured(jv, math.hypot(js_, spread),
                                           "weighted mean of " + " and ".join(f"the {n} ({j.value:.4g})" for n, j in js))


# ---------------------------------------------------------------------------
# the profile it writes
# ---------------------------------------------------------------------------
def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        return repr(float(f"{v:.6g}"))
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise TypeError(f"cannot write {v!r} as TOML")


def _toml_tables(d: dict, prefix: str, out: list[str], comments: dict) -> None:
    scalars = {k: v for k, v in d.items() if not isinstance(v, dict)}
    tables = {k: v for k, v in d.items() if isinstance(v, dict)}
    if prefix and scalars:
        out.append(f"\n[{prefix}]")
    for k, v in scalars.items():
        c = comments.get(f"{prefix}.{k}")
        out.append(f"{k} = {_toml_value(v)}" + (f"    # {c}" if c else ""))
    for k, v in tables.items():
        _toml_tables(v, f"{prefix}.{k}" if prefix else k, out, comments)


def profile_text(source_text: str, res: Identification, source_name: str) -> str:
    """The identified profile: the input's sections with [motor]'s measured values replaced
    (line-to-line R and L), [sensors] hall_offset_deg and encoder_lines measured, each with its
    uncertainty as a comment."""
    raw = tomllib.loads(source_text)
    mot = dict(raw.get("motor", {}))
    sen = dict(raw.get("sensors", {}))
    v = res.values
    com = {}

    def put(sec: dict, secname: str, key: str, name: str, unit: str):
        if name in v:
            x = v[name]
            sec[key] = float(x.value) if not isinstance(sec.get(key), int) else int(round(x.value))
            com[f"{secname}.{key}"] = f"measured: +- {x.sigma:.2g} {unit}" if x.sigma else "measured"
    if "resistance_line_ohm" in v:
        # both winding values on the line-to-line basis the measurement gives
        if mot.get("winding_basis", "phase") != "line-to-line":
            f = 2.0
            for k in ("inductance_h", "ld_h", "lq_h"):
                if k in mot:
                    mot[k] = mot[k] * f
            mot["winding_basis"] = "line-to-line"
        put(mot, "motor", "resistance_ohm", "resistance_line_ohm", "ohm")
    if "inductance_line_h" in v:
        for k in ("ld_h", "lq_h"):
            mot.pop(k, None)
        put(mot, "motor", "inductance_h", "inductance_line_h", "H")
    if "back_emf_constant_v_s" in v:
        mot.pop("flux_linkage_v_s", None)
        put(mot, "motor", "back_emf_constant_v_s", "back_emf_constant_v_s", "V s/rad")
        put(mot, "motor", "torque_constant_n_m_per_a", "torque_constant_n_m_per_a", "N m/A")
    put(mot, "motor", "inertia_kg_m2", "inertia_kg_m2", "kg m^2")
    if "viscous_friction_n_m_s" in v:
        mot["viscous_friction_n_m_s"] = max(float(v["viscous_friction_n_m_s"].value), 0.0)
        com["motor.viscous_friction_n_m_s"] = f"measured: +- {v['viscous_friction_n_m_s'].sigma:.2g} N m s/rad"
    put(sen, "sensors", "hall_offset_deg", "hall_offset_deg", "deg")
    if "hall_offset_deg" in v:
        sen["hall_offset_deg"] = float(v["hall_offset_deg"].value)
    if "encoder_lines" in v:
        sen["encoder_lines"] = int(round(v["encoder_lines"].value))
        com["sensors.encoder_lines"] = "measured"
    raw["motor"] = mot
    raw["sensors"] = sen
    lines = [f"# identified by 'picdrive identify' from {source_name}: [motor] values and the hall offset / encoder",
             "# lines measured on the board (see the comments); the other sections are the input's."]
    for name, x in v.items():
        lines.append(f"#   {name} = {x.value:.6g} +- {x.sigma:.2g}: {x.how}")
    for n in res.notes:
        lines.append(f"#   note: {n}")
    body: list[str] = []
    top = {k: val for k, val in raw.items() if not isinstance(val, dict)}
    for k, val in top.items():
        body.append(f"{k} = {_toml_value(val)}")
    _toml_tables({k: val for k, val in raw.items() if isinstance(val, dict)}, "", body, com)
    return "\n".join(lines) + "\n" + "\n".join(body).lstrip("\n").replace("\n[", "\n\n[", 0) + "\n"


def summary_text(res: Identification) -> str:
    units = {"resistance_line_ohm": "ohm (line-to-line)", "inductance_line_h": "H (line-to-line)",
             "back_emf_constant_v_s": "V s/rad", "torque_constant_n_m_per_a": "N m/A", "inertia_kg_m2": "kg m^2",
             "viscous_friction_n_m_s": "N m s/rad", "coulomb_friction_n_m": "N m", "hall_offset_deg": "deg",
             "encoder_lines": "lines", "freewheel_drop_v": "V"}
    out = []
    for k, x in res.values.items():
        out.append(f"{k:28s} {x.value:12.6g} +- {x.sigma:9.2g} {units.get(k, '')}")
        out.append(f"{'':28s} {x.how}")
    if res.hall_table is not None:
        out.append("hall table (code: forward, reverse): " + ", ".join(
            f"{c:03b}: {res.hall_table.describe(c, 0)} / {res.hall_table.describe(c, 1)}"
            for c in range(8) if res.hall_table.forward[c] is not None))
    out += [f"note: {n}" for n in res.notes]
    return "\n".join(out)


# ---------------------------------------------------------------------------
# command line
# ---------------------------------------------------------------------------
def register(subparsers) -> None:
    p = subparsers.add_parser(
        "identify", help="measure the motor on the board and write the profile it makes",
        description="Measure the motor's hall table and offset, encoder lines, R and L (line-to-line), Kb = Kt, "
                    "J and friction on the board, and write a profile with those values that 'picdrive design' "
                    "takes.  The board runs the identification firmware of this profile ('picdrive firmware "
                    "--identify'); flash the drive firmware back afterwards.")
    p.add_argument("url", help="serial URL of the board or the twin (/dev/ttyUSB0, COM5, socket://HOST:PORT)")
    p.add_argument("--profile", required=True, help="the drive profile (name or path): its [inverter], [sensors] "
                                                   "and [control] describe the board; its [motor] may be rough")
    p.add_argument("-o", "--out", required=True, help="the identified profile to write (.toml)")
    p.set_defaults(func=main)


def _same_kind(path: Path) -> bool:
    try:
        return path.read_text(errors="replace").startswith("# identified by 'picdrive identify'")
    except OSError:
        return False


def main(args) -> int:
    from .. import outputs
    from ..fileio import read_input_text
    from ..link.client import Link
    from ..profile import load_profile, loads_profile, resolve_profile_path
    ppath = resolve_profile_path(args.profile)
    prof = load_profile(ppath)
    text = read_input_text(ppath, "profile", limit_bytes=1 << 20)
    out = outputs.file_output(args.out, Path(f"{prof.name}.identified.toml"), what="identified profile",
                              same_kind=_same_kind)
    try:
        link = Link.open(args.url)
    except Exception as e:                                        # noqa: BLE001 - named to the user
        raise IdentifyError(f"cannot open {args.url}: {e}") from None
    try:
        info = link.handshake()
        print(f"connected to {args.url}: firmware build 0x{info.build_id:08x}")
        try:
            res = identify(link, prof)
        except IdentifyError as e:
            part = getattr(e, "partial", None)
            if part is not None and part.values:
                print("measured before the stop (nothing written):\n" + summary_text(part))
            raise
        except KeyboardInterrupt:
            print("interrupted: the motor was stopped; nothing written")
            return 130
    finally:
        link.close()
    print(summary_text(res))
    new = profile_text(text, res, str(ppath))
    loads_profile(new)            # it loads as 'picdrive design' will load it, or nothing is written
    outputs.write_text(out, new, what="identified profile")
    print(f"wrote {out}")
    return 0
