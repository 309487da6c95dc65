"""Drive profile: one TOML file describing one BLDC drive.

A profile holds the motor, the inverter, the sensors, the loop rates, the
speed range and the controller-design settings.  Everything downstream
(design, firmware, twin, console) reads its numbers from here and nowhere
else.  The schema is documented field by field in ``docs/profile.md``; the
table :data:`SCHEMA` below is the single source of truth for names, units,
defaults and accepted ranges.

All quantities are SI with the unit in the field name (``_ohm``, ``_h``,
``_kg_m2``...).  Speeds at the user interface are in rpm (mechanical);
inside the models they are rad/s.

Winding basis: ``motor.winding_basis = "phase"`` means ``resistance_ohm`` and
``inductance_h`` (or ``ld_h``/``lq_h``) are per-phase values of a
wye-connected machine (the 2016 paper's dq model); ``"line-to-line"`` means
terminal-to-terminal values, i.e. two phases in series, which is what the DC
equivalent transfer function of a six-step drive uses (the 2008 paper's
eq. 1).  :class:`Motor` exposes both forms.
"""
from __future__ import annotations

import dataclasses
import hashlib
import math
import re
import tomllib
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .errors import PicdriveError
from .fileio import read_input_text

SCHEMA_ID = "picdrive.profile/1"

__all__ = [
    "ProfileError", "ProfileWarning", "Profile", "Motor", "Inverter",
    "Sensors", "Control", "Uart", "load_profile", "loads_profile",
    "bundled_profiles", "resolve_profile_path", "SCHEMA", "hash32", "BusGuard", "bus_guard",
    "BUS_GUARD_LEVELS", "BUS_SUPPLY_MARGIN",
]


class ProfileError(PicdriveError, ValueError):
    """A profile field is missing, mistyped or non-physical.

    The message names the field, the value found and the accepted range.
    """


class ProfileWarning(UserWarning):
    """A profile is valid but asks for something the drive cannot deliver."""


# ---------------------------------------------------------------------------
# Schema: section -> field -> (kind, default, lo, hi, doc)
#   kind: "float", "int", "str", "bool", "enum:a|b", "range" (2-list of float),
#         "list-int"
#   default REQUIRED means the field must be given.
#   lo/hi are inclusive physical bounds (None = unbounded); for "range" they
#   bound both ends.
# ---------------------------------------------------------------------------
REQUIRED = object()

SCHEMA: dict[str, dict[str, tuple]] = {
    "drive": {
        "name": ("str", REQUIRED, None, None, "identifier used for file and folder names: lowercase letters, digits, '_' and '-'"),
        "description": ("str", "", None, None, "one line describing the drive"),
        "source": ("str", "", None, None, "where the numbers come from"),
    },
    "motor": {
        "pole_pairs": ("int", REQUIRED, 1, 64, "number of pole pairs P"),
        "winding_basis": ("enum:phase|line-to-line", "phase", None, None, "basis of resistance_ohm / inductance_h"),
        "resistance_ohm": ("float", REQUIRED, 1e-4, 1e3, "stator resistance on winding_basis, ohm"),
        "inductance_h": ("float", None, 1e-7, 10.0, "stator inductance on winding_basis, H (sets ld_h = lq_h)"),
        "ld_h": ("float", None, 1e-7, 10.0, "d-axis inductance on winding_basis, H"),
        "lq_h": ("float", None, 1e-7, 10.0, "q-axis inductance on winding_basis, H"),
        "inertia_kg_m2": ("float", REQUIRED, 1e-9, 100.0, "rotor + load inertia J, kg m^2"),
        "viscous_friction_n_m_s": ("float", REQUIRED, 0.0, 100.0, "viscous friction B, N m s/rad"),
        "flux_linkage_v_s": ("float", None, 1e-5, 10.0, "permanent-magnet flux linkage lambda_m, V s/rad (electrical), phase peak"),
        "torque_constant_n_m_per_a": ("float", None, 1e-5, 100.0, "six-step DC-equivalent torque constant Kt, N m/A"),
        "back_emf_constant_v_s": ("float", None, 1e-5, 100.0, "six-step DC-equivalent back-EMF constant Kb, V s/rad (mechanical), line-to-line"),
        "back_emf_shape": ("enum:trapezoidal|sinusoidal", "trapezoidal", None, None, "back-EMF waveform"),
        "rated_current_a": ("float", REQUIRED, 1e-3, 500.0, "continuous current rating, A"),
    },
    "inverter": {
        "bus_voltage_v": ("float", REQUIRED, 1.0, 600.0, "DC bus voltage, V"),
        "current_limit_a": ("float", REQUIRED, 1e-3, 500.0, "firmware current limit, A"),
        "overcurrent_trip_a": ("float", REQUIRED, 1e-3, 1000.0, "hardware comparator trip level on FLTA, A"),
        "pwm_frequency_hz": ("float", 20000.0, 1000.0, 100000.0, "PCPWM switching frequency, Hz"),
        "dead_time_ns": ("float", 1000.0, 0.0, 10000.0, "dead time inserted by DTCON between complementary switches, ns"),
        "bootstrap_refresh_ns": ("float", 2000.0, 0.0, 50000.0, "minimum low-side on-time per PWM period that keeps the IR2101 bootstrap capacitor charged, ns"),
        "current_sense_v_per_a": ("float", 0.1, 1e-4, 10.0, "bus-current sense gain at the ADC pin, V/A"),
        "gate_driver": ("str", "IR2101", None, None, "gate driver part"),
        "switch": ("str", "IRF540", None, None, "MOSFET part"),
        "switch_vds_max_v": ("float", 100.0, 1.0, 2000.0, "MOSFET drain-source rating, V"),
        "bus_capacitance_f": ("float", 470e-6, 1e-6, 1.0, "DC-bus bulk capacitance, F: the bus rises on it when "
                              "the bridge returns energy the supply cannot take (default: the reference board's "
                              "470 uF)"),
        "supply_sink_a": ("float", 0.0, 0.0, 1000.0, "current the supply can take back, A: 0 for a bench supply "
                          "or a rectifier, a battery's charge current"),
        "brake_resistor_ohm": ("float", 0.0, 0.0, 1e4, "brake resistor switched across the bus by a hardware "
                               "chopper, ohm; 0 = none"),
        "bus_sense_v_per_v": ("float", 0.0, 0.0, 1.0, "bus-voltage divider at the AN1 pin, V per V of bus; "
                              "0 = one that puts the nominal bus at 2.5 V (half the 5 V ADC reference)"),
        "brake_chopper_v": ("float", 0.0, 0.0, 2000.0, "bus voltage above which the chopper connects the brake "
                            "resistor, V; 0 = 110 % of bus_voltage_v"),
    },
    "sensors": {
        "hall_spacing_deg": ("int", 120, 60, 120, "electrical spacing of the hall sensors: 60 or 120"),
        "hall_offset_deg": ("float", 0.0, -180.0, 180.0, "electrical angle of hall A's rising edge after phase A back-EMF zero crossing, deg"),
        "encoder_lines": ("int", 0, 0, 65535, "encoder lines per revolution (0 = no encoder)"),
        "speed_source": ("enum:encoder|hall", "encoder", None, None, "speed feedback for the speed loop"),
        "speed_noise_rpm": ("float", 0.0, 0.0, 1000.0, "standard deviation of speed-measurement noise in the twin, rpm"),
    },
    "control": {
        "speed_loop_hz": ("float", 1000.0, 10.0, 20000.0, "speed-loop rate, Hz"),
        "speed_min_rpm": ("float", 0.0, 0.0, 1e5, "lowest commanded speed, rpm"),
        "speed_max_rpm": ("float", REQUIRED, 1.0, 1e5, "highest commanded speed, rpm"),
        "reference_rpm": ("float", REQUIRED, 0.0, 1e5, "nominal speed step target, rpm"),
        "load_torque_n_m": ("float", 0.0, 0.0, 1e3, "load-torque step used by demos and tests, N m"),
        "stall_timeout_ms": ("float", 500.0, 10.0, 60000.0, "commanded with no motion for this long = stall fault, ms"),
        "reference_feedforward": ("enum:off|on|auto", "off", None, None, "preload the law's integrator by the "
                                  "no-load steady-state voltage of each reference change "
                                  "(picdrive.control_law.reference_ff_gain), set on the law at verification; 'auto': "
                                  "only on a law that verifies without it, when the verification's steps from rest (no "
                                  "load and the profile's load) reach the 1 % band sooner with it, overshoot no more "
                                  "than 1 % (or than without), and the law with it passes every check"),
    },
    "uart": {
        "baud": ("int", 115200, 1200, 1000000, "EUSART baud rate"),
        "link_timeout_ms": ("float", 500.0, 20.0, 60000.0, "link-loss watchdog timeout while running, ms"),
    },
    "design": {
        # common
        "premise_rpm": ("range", [0.0, 3000.0], 0.0, 1e5, "fuzzy premise (speed) range [N1, N2], rpm"),
        "rules": ("int", 2, 1, 8, "number of fuzzy rules r (1 = plain PID)"),
        "plant_model": ("enum:averaged|six-step", "averaged", None, None,
                        "fuzzy-hinf six-step design's plant: the speed-dependent averaged model identified from the "
                        "three-phase plant, or the DC equivalent (docs/scheduling.md); --option plant_model overrides"),
        # fuzzy H-inf (2016)
        "gamma": ("float", 1.0, 1e-6, 1e6, "prescribed H-inf level gamma"),
        "delta": ("float", 1.0, 1e-6, 1e6, "Theorem 1 scaling delta"),
        "alpha": ("float", 2.0, 1e-6, 1e6, "Theorem 1 weight alpha"),
        "rho": ("float", 1.0, 0.0, 1e6, "uncertainty bound rho on ||F||"),
        "resistance_uncertainty": ("float", 0.1, 0.0, 1.0, "relative bound of R uncertainty (0.1 = +-10 %)"),
        # mixed H2/H-inf PID (2008)
        "kp_range": ("range", [0.0, 200.0], -1e6, 1e6, "GA search bounds of kp"),
        "ki_range": ("range", [0.0, 10.0], -1e6, 1e6, "GA search bounds of ki"),
        "kd_range": ("range", [0.0, 0.1], -1e6, 1e6, "GA search bounds of kd"),
        "perturbation_d": ("float", 0.1, 0.0, 1e6, "plant perturbation parameter d of xi(s) = d/(s^2+0.1s+10)"),
        "ga_population": ("int", 200, 4, 100000, "GA population size"),
        "ga_generations": ("int", 20, 1, 100000, "GA generations"),
        "ga_seed": ("int", 1, 0, 2**31 - 1, "GA random seed"),
    },
}

#: Kt / Kb may differ by this fraction (datasheet rounding, measurement); beyond it the two
#: numbers cannot both be SI values of the same DC-equivalent motor
KT_KB_TOLERANCE = 0.10

# (ratio Kt/Kb the slip produces, what the user most likely typed), checked against the ratio found
_KT_KB_SLIPS = (
    (1000.0, "Kt looks like mN m/A (divide it by 1000 for N m/A)"),
    (1e-3, "Kb looks like mV s/rad (divide it by 1000 for V s/rad)"),
    (100.0, "Kt looks like N cm/A (divide it by 100 for N m/A)"),
    (1 / 0.0980665, "Kt looks like kg cm/A (multiply it by 0.0981 for N m/A)"),
    (1 / 0.00706155, "Kt looks like oz in/A (multiply it by 0.00706 for N m/A)"),
    (1 / 0.112985, "Kt looks like lb in/A (multiply it by 0.113 for N m/A)"),
    (60 / (2 * math.pi * 1000), "Kb looks like V/krpm (multiply it by 60 / (2 pi 1000) = 0.00955 for V s/rad)"),
    (60 / (2 * math.pi), "Kb looks like V/rpm (multiply it by 60 / (2 pi) = 9.55 for V s/rad)"),
    (2.0, "Kb looks like a phase value: the six-step Kb is line-to-line, twice a trapezoidal motor's phase value"),
    (math.sqrt(3.0), "Kb looks like a phase value of a sinusoidal motor (line-to-line is sqrt 3 times it)"),
    (math.sqrt(2.0), "one constant looks like an RMS value and the other a peak value (factor sqrt 2)"),
    (1 / math.sqrt(2.0), "one constant looks like an RMS value and the other a peak value (factor sqrt 2)"),
)


def _kt_kb_slip(ratio: float) -> str:
    """The unit slip whose factor is nearest (in log) to the ratio Kt/Kb found."""
    d, text = min((abs(math.log(ratio / f)), t) for f, t in _KT_KB_SLIPS)
    if d > math.log(1.15):
        return "no common unit slip gives this ratio: check both constants against the datasheet"
    return text


#: a profile is a few kB of TOML; anything far larger is the wrong file (read no further)
PROFILE_MAX_BYTES = 1 << 20

#: The design's verification (picdrive.analysis.steptest.sim_plan) simulates a step from rest and
#: then a load step, each phase lasting this many times the drive's fastest step from rest
#: (:meth:`Profile.min_step_time_s`; at least 0.6 s), one integration step per PWM period, in
#: Python, several runs per design: its length, memory and run time grow with that time.
VERIFY_PHASE_PER_MIN_STEP = 3.0
#: The most PWM periods one verification run may simulate: 2e6 periods keep its arrays (4 float64
#: per period, 12 per speed-loop sample) near 70 MiB and its run time near a minute of one core,
#: while the bundled drives need 24 000 (1.2 s at 20 kHz).  A profile beyond it is refused before
#: any computation, with its figures and the likely unit slip.
VERIFY_MAX_PWM_PERIODS = 2_000_000
_SIM_BYTES_PER_PWM_PERIOD = 4 * 8
_SIM_BYTES_PER_SAMPLE = 12 * 8 + 1

# (factor to kg m^2, the unit) of the inertia units found on datasheets, most common first
_INERTIA_UNITS = ((1e-4, "kg cm^2"), (1e-7, "g cm^2"), (1e-6, "kg mm^2"), (1e-9, "g mm^2"),
                  (1.8290e-5, "oz in^2"), (2.9264e-4, "lb in^2"))


def _inertia_slip(p: "Profile", fits) -> str:
    """The inertia units that would make the profile plausible (``fits(J)``), as advice."""
    j = p.motor.inertia_kg_m2
    hits = [f"{unit} (x {f:g}: J = {j * f:.3g} kg m^2)" for f, unit in _INERTIA_UNITS
            if j * f >= SCHEMA["motor"]["inertia_kg_m2"][2] and fits(j * f)]
    if not hits:
        return ("no common unit slip of J makes it plausible: check motor.inertia_kg_m2, the torque constant and "
                "inverter.current_limit_a against the datasheet")
    return f"J looks like a value in {' or '.join(hits[:2])}; give the inertia in kg m^2"


def _check_simulation_size(p: "Profile") -> None:
    """Refuse a profile whose verification simulation would be absurdly long (a unit slip in J)."""
    t_min = p.min_step_time_s()
    if not math.isfinite(t_min):
        return                     # the current limit cannot carry the load: the design refuses that itself
    hz = p.inverter.pwm_frequency_hz

    def periods(t):
        return 2.0 * VERIFY_PHASE_PER_MIN_STEP * t * hz
    n = periods(t_min)
    if n <= VERIFY_MAX_PWM_PERIODS:
        return
    m = p.motor
    window = n / hz
    mem = n * _SIM_BYTES_PER_PWM_PERIOD + window * p.control.speed_loop_hz * _SIM_BYTES_PER_SAMPLE
    tau_m = m.inertia_kg_m2 * m.r_line_ohm / (m.kt_n_m_per_a * m.kb_v_s_per_rad)
    raise ProfileError(
        f"profile field 'motor.inertia_kg_m2' = {m.inertia_kg_m2:g} kg m^2 is implausible for this motor: with "
        f"Kt = {m.kt_n_m_per_a:.4g} N m/A at inverter.current_limit_a = {p.inverter.current_limit_a:g} A, its "
        f"fastest step from rest to {p.speed_step_rpm():.0f} rpm takes {t_min:.3g} s (mechanical time constant "
        f"J R / (Kt Kb) = {tau_m:.3g} s), so the design's verification would simulate {window:.3g} s in "
        f"{n:.3g} PWM periods (about {mem / 2**20:.0f} MiB per run and a long run time), beyond its bound of "
        f"{VERIFY_MAX_PWM_PERIODS:g} periods ({VERIFY_MAX_PWM_PERIODS / hz:g} s at {hz:g} Hz); "
        + _inertia_slip(p, lambda j: periods(t_min * j / m.inertia_kg_m2) <= VERIFY_MAX_PWM_PERIODS))


_NAME_RE = re.compile(r"^[a-z0-9][a-z0-9_-]{0,47}$")


# ---------------------------------------------------------------------------
# Dataclasses (frozen): the validated profile
# ---------------------------------------------------------------------------
@dataclass(frozen=True)
class Motor:
    pole_pairs: int
    winding_basis: str
    resistance_ohm: float
    ld_h: float
    lq_h: float
    inertia_kg_m2: float
    viscous_friction_n_m_s: float
    flux_linkage_v_s: float | None
    torque_constant_n_m_per_a: float | None
    back_emf_constant_v_s: float | None
    back_emf_shape: str
    rated_current_a: float

    # -- per-phase and line-to-line forms ---------------------------------
    @property
    def _to_phase(self) -> float:
        return 0.5 if self.winding_basis == "line-to-line" else 1.0

    @property
    def r_phase_ohm(self) -> float:
        """Per-phase resistance of the equivalent wye winding, ohm."""
        return self.resistance_ohm * self._to_phase

    @property
    def ld_phase_h(self) -> float:
        return self.ld_h * self._to_phase

    @property
    def lq_phase_h(self) -> float:
        return self.lq_h * self._to_phase

    @property
    def r_line_ohm(self) -> float:
        """Terminal (two phases in series) resistance, ohm: the six-step DC equivalent."""
        return 2.0 * self.r_phase_ohm

    @property
    def l_line_h(self) -> float:
        """Terminal inductance (two phases in series, average of Ld and Lq), H."""
        return self.ld_phase_h + self.lq_phase_h

    # -- EMF / torque constants ------------------------------------------
    @property
    def _dc_factor(self) -> float:
        # Six-step DC-equivalent line-to-line EMF per (P * lambda_m * w_mech):
        # trapezoidal: two flat tops in series -> 2; sinusoidal: mean of the
        # line-to-line sine over each 60 deg conduction window -> 3*sqrt(3)/pi.
        return 2.0 if self.back_emf_shape == "trapezoidal" else 3.0 * math.sqrt(3.0) / math.pi

    @property
    def kb_v_s_per_rad(self) -> float:
        """Six-step DC-equivalent back-EMF constant, V per mechanical rad/s.

        The one DC-equivalent constant every model uses: in SI units Kt = Kb
        (the same flux makes the EMF and the torque), so the design's Kt, the
        verification's Kb and the twin's flux linkage all come from it.  From
        the profile's ``back_emf_constant_v_s`` when given (the load checked
        that ``torque_constant_n_m_per_a`` agrees within
        :data:`KT_KB_TOLERANCE`), else the torque constant, else the flux
        linkage."""
        if self.back_emf_constant_v_s is not None:
            return self.back_emf_constant_v_s
        if self.torque_constant_n_m_per_a is not None:
            return self.torque_constant_n_m_per_a  # ideal machine, SI: Kb = Kt
        return self._dc_factor * self.pole_pairs * self.flux_linkage_v_s  # type: ignore[operator]

    @property
    def kt_n_m_per_a(self) -> float:
        """Six-step DC-equivalent torque constant, N m per A of line current: the same
        constant as :attr:`kb_v_s_per_rad` (SI), so design and twin model one motor."""
        return self.kb_v_s_per_rad

    @property
    def lambda_m_v_s(self) -> float:
        """PM flux linkage, V s per electrical rad (phase peak), for the dq model."""
        if self.flux_linkage_v_s is not None:
            return self.flux_linkage_v_s
        return self.kb_v_s_per_rad / (self._dc_factor * self.pole_pairs)


@dataclass(frozen=True)
class Inverter:
    bus_voltage_v: float
    current_limit_a: float
    overcurrent_trip_a: float
    pwm_frequency_hz: float
    dead_time_ns: float
    bootstrap_refresh_ns: float
    current_sense_v_per_a: float
    gate_driver: str
    switch: str
    switch_vds_max_v: float
    bus_capacitance_f: float = 470e-6
    supply_sink_a: float = 0.0
    brake_resistor_ohm: float = 0.0
    brake_chopper_v: float = 0.0
    bus_sense_v_per_v: float = 0.0


@dataclass(frozen=True)
class Sensors:
    hall_spacing_deg: int
    hall_offset_deg: float
    encoder_lines: int
    speed_source: str
    speed_noise_rpm: float

    @property
    def has_encoder(self) -> bool:
        return self.encoder_lines > 0


@dataclass(frozen=True)
class Control:
    speed_loop_hz: float
    speed_min_rpm: float
    speed_max_rpm: float
    reference_rpm: float
    load_torque_n_m: float
    stall_timeout_ms: float
    reference_feedforward: str = "off"


@dataclass(frozen=True)
class Uart:
    baud: int
    link_timeout_ms: float


def hash32(sha256_hex: str) -> int:
    """The firmware's 32-bit profile hash of a profile SHA-256 (hex): its first 4 bytes, 0 for ''."""
    return int(sha256_hex[:8], 16) if sha256_hex else 0


@dataclass(frozen=True)
class Profile:
    """A validated drive profile.  Build with :func:`load_profile`."""

    name: str
    description: str
    source: str
    motor: Motor
    inverter: Inverter
    sensors: Sensors
    control: Control
    uart: Uart
    design: dict[str, Any]
    path: Path | None = None
    sha256: str = ""
    raw: dict[str, Any] = field(default_factory=dict, repr=False, compare=False)
    #: the production tolerances (``[tolerances]``, defaults filled in: :mod:`picdrive.tolerances`)
    tolerances: dict[str, Any] = field(default_factory=dict, repr=False, compare=False)
    #: the seed of one drive off the line (``[as_built]``): the twin runs that drive; None for the nominal
    as_built_seed: int | None = None

    # -- derived quantities used in several places ------------------------
    @property
    def hash32(self) -> int:
        """The profile hash the firmware carries (``profile_hash`` in hello and board.json): the first
        4 bytes of :attr:`sha256` as an unsigned integer, 0 when the profile has no hash."""
        return hash32(self.sha256)

    def max_reachable_rpm(self, load_torque_n_m: float = 0.0) -> float:
        """Highest steady speed the bridge can hold against a load torque, rpm.

        Back-EMF plus the IR drop of the current that carries friction and
        load equals the usable bus voltage (bus voltage x :meth:`max_duty`):
        ``V = Kb w + R_line (B w + T_load) / Kt``.

        This is the six-step DC equivalent (2008 eq 1): it ignores commutation.
        Where a hall sector lasts less than the winding's L/R the current cannot
        follow the sectors and the real bridge holds less; the twin measures it
        (docs/twin.md).
        """
        m, inv = self.motor, self.inverter
        v = inv.bus_voltage_v * self.max_duty() - m.r_line_ohm * load_torque_n_m / m.kt_n_m_per_a
        w = v / (m.kb_v_s_per_rad + m.r_line_ohm * m.viscous_friction_n_m_s / m.kt_n_m_per_a)
        return max(0.0, w) * 60.0 / (2.0 * math.pi)

    def max_duty(self) -> float:
        """Largest PWM duty (0..1) that leaves dead time plus the bootstrap
        refresh time as low-side on-time in every period."""
        inv = self.inverter
        period_ns = 1e9 / inv.pwm_frequency_hz
        return max(0.0, 1.0 - (inv.bootstrap_refresh_ns + 2.0 * inv.dead_time_ns) / period_ns)

    def speed_step_rpm(self) -> float:
        """Speed step target used by demos and tests: the reference speed, or,
        where the bridge cannot hold it under the profile's load torque, 95 %
        of the speed it can hold (5 % voltage headroom for the speed loop)."""
        return min(self.control.reference_rpm,
                   0.95 * self.max_reachable_rpm(self.control.load_torque_n_m))

    def min_step_time_s(self, rpm: float | None = None) -> float:
        """The fastest the drive can reach ``rpm`` (default :meth:`speed_step_rpm`) from rest at the
        current limit, ``t_min = J w / (Kt I_lim - T_load)``, s (inf when the limit cannot carry the load)."""
        m = self.motor
        w = (self.speed_step_rpm() if rpm is None else rpm) * 2.0 * math.pi / 60.0
        net = m.kt_n_m_per_a * self.inverter.current_limit_a - self.control.load_torque_n_m
        return m.inertia_kg_m2 * w / net if net > 0 else math.inf

    def to_dict(self) -> dict[str, Any]:
        """The profile as plain data (all fields resolved, defaults filled in)."""
        return {
            "schema": SCHEMA_ID,
            "drive": {"name": self.name, "description": self.description, "source": self.source},
            "motor": dataclasses.asdict(self.motor),
            "inverter": dataclasses.asdict(self.inverter),
            "sensors": dataclasses.asdict(self.sensors),
            "control": dataclasses.asdict(self.control),
            "uart": dataclasses.asdict(self.uart),
            "design": dict(self.design),
        }

    def replace(self, **sections: dict[str, Any]) -> "Profile":
        """A copy with some fields changed, re-validated.

        ``p.replace(motor={"resistance_ohm": 0.55})`` gives the same profile
        with R changed (useful for perturbation studies).
        """
        raw = {k: dict(v) if isinstance(v, dict) else v for k, v in self.raw.items()}
        for sec, fields_ in sections.items():
            raw.setdefault(sec, {}).update(fields_)
        return _build(raw, self.path, _hash_raw(raw))


# ---------------------------------------------------------------------------
# The bus guard: sense divider and regeneration levels, derived once
# ---------------------------------------------------------------------------
BUS_GUARD_LEVELS: dict[str, tuple[float, float]] = {
    "taper_start": (1.10, 0.80),
    "taper_end": (1.20, 0.85),
    "trip": (1.25, 0.90),
}
"""Each bus level as (fraction of ``inverter.bus_voltage_v``, fraction of
``inverter.switch_vds_max_v``): the level is the lower of the two.  Braking
current is full up to ``taper_start``, scaled down linearly to 0 at
``taper_end``; above ``trip`` an OVERVOLTAGE fault latches (outputs off).  The
switch fraction keeps the peak below 90 % of the rating; the bus fraction
keeps the capacitors and the supply within 125 % of the nominal bus (VESC's
``l_battery_regen_cut_start``/``_end`` and ``l_max_vin``, ODrive's
``dc_bus_overvoltage_trip_level``)."""

BUS_SUPPLY_MARGIN = 1.05
"""The taper must start at least this factor above the supply's bus voltage:
below it supply tolerance and ripple would cut braking that returns nothing."""

BUS_UNDERVOLTAGE = 0.70
"""Undervoltage level while running, fraction of ``inverter.bus_voltage_v``."""

_ADC_COUNTS, _ADC_VREF_V = 1024, 5.0     # the PIC18F4431's 10-bit converter on AN1


@dataclass(frozen=True)
class BusGuard:
    """Bus sense and guard levels of one inverter (V, and ADC counts on AN1).

    ``source`` says where the divider came from (``"inverter.bus_sense_v_per_v"``
    or ``"assumed"``); ``problem`` is empty when the guard window is sensible,
    else the reason it is not (:func:`bus_guard` with ``strict=True`` raises it).
    """
    bus_sense_v_per_v: float
    source: str
    counts_per_v: float
    bus_v: float
    switch_v: float
    uv_v: float
    taper_start_v: float
    taper_end_v: float
    trip_v: float
    uv: int
    taper_start: int
    taper_end: int
    trip: int
    problem: str = ""

    def lines(self) -> list[str]:
        """The levels as text, each with its derivation (``picdrive firmware`` prints them)."""
        def one(name, v, c):
            fb, fs = BUS_GUARD_LEVELS[name]
            return (f"{name:<12}{v:7.1f} V = {c:4d} counts  (min of {fb:.2f} x bus {self.bus_v:g} V, "
                    f"{fs:.2f} x switch {self.switch_v:g} V)")
        return [one("taper_start", self.taper_start_v, self.taper_start),
                one("taper_end", self.taper_end_v, self.taper_end),
                one("trip", self.trip_v, self.trip),
                f"{'undervolt':<12}{self.uv_v:7.1f} V = {self.uv:4d} counts  ({BUS_UNDERVOLTAGE:.2f} x bus, running)"]


def bus_guard(inverter: "Inverter", strict: bool = True) -> BusGuard:
    """Bus-voltage sense on AN1 and the regeneration guard's levels.

    Parameters
    ----------
    inverter : Inverter
        ``bus_voltage_v``, ``switch_vds_max_v`` (V) and ``bus_sense_v_per_v``
        (V/V; 0: a divider that puts the nominal bus at 2.5 V is assumed).
    strict : bool
        Raise :class:`ProfileError` when no sensible window exists (the taper
        would start less than :data:`BUS_SUPPLY_MARGIN` above the supply, the
        levels would not be distinct ADC counts, or the trip would be beyond
        the ADC's range).

    Returns
    -------
    BusGuard
        Levels in V (:data:`BUS_GUARD_LEVELS`) and in ADC counts.
    """
    vb, vs = inverter.bus_voltage_v, inverter.switch_vds_max_v
    given = inverter.bus_sense_v_per_v > 0.0
    ratio = inverter.bus_sense_v_per_v if given else 2.5 / vb
    cpv = ratio * _ADC_COUNTS / _ADC_VREF_V
    lv = {k: min(fb * vb, fs * vs) for k, (fb, fs) in BUS_GUARD_LEVELS.items()}
    cnt = {k: min(1023, int(math.ceil(v * cpv))) for k, v in lv.items()}
    problem = ""
    if lv["taper_start"] < BUS_SUPPLY_MARGIN * vb:
        problem = (f"profile fields 'inverter.bus_voltage_v' = {vb:g} V and 'inverter.switch_vds_max_v' = {vs:g} V "
                   f"leave no regeneration window: braking would taper from {lv['taper_start']:.1f} V "
                   f"({BUS_GUARD_LEVELS['taper_start'][1]:.2f} x the switch rating), less than "
                   f"{BUS_SUPPLY_MARGIN:.2f} x the bus ({BUS_SUPPLY_MARGIN * vb:.1f} V); use switches rated at least "
                   f"{BUS_SUPPLY_MARGIN * vb / BUS_GUARD_LEVELS['taper_start'][1]:.0f} V or a lower bus")
    elif not cnt["taper_start"] < cnt["taper_end"] < cnt["trip"] < 1023:
        problem = (f"profile field 'inverter.bus_sense_v_per_v' = {ratio:.5g} V/V: the bus guard's levels "
                   f"({lv['taper_start']:.1f}, {lv['taper_end']:.1f}, {lv['trip']:.1f} V) come out as ADC counts "
                   f"{cnt['taper_start']}, {cnt['taper_end']}, {cnt['trip']}, not distinct below full scale 1023: "
                   f"a divider of at most {4.9 / lv['trip']:.4g} V/V that still resolves them")
    if problem and strict:
        raise ProfileError(problem)
    uv_v = BUS_UNDERVOLTAGE * vb
    return BusGuard(bus_sense_v_per_v=ratio, source="inverter.bus_sense_v_per_v" if given else "assumed",
                    counts_per_v=cpv, bus_v=vb, switch_v=vs, uv_v=uv_v,
                    taper_start_v=lv["taper_start"], taper_end_v=lv["taper_end"], trip_v=lv["trip"],
                    uv=int(math.floor(uv_v * cpv)), taper_start=cnt["taper_start"], taper_end=cnt["taper_end"],
                    trip=cnt["trip"], problem=problem)


# ---------------------------------------------------------------------------
# Loading and validation
# ---------------------------------------------------------------------------
def _fail(where: str, value: Any, expect: str) -> ProfileError:
    return ProfileError(f"profile field '{where}' = {value!r}: {expect}")


def _range_text(lo, hi) -> str:
    if lo is not None and hi is not None:
        return f"a number in [{lo:g}, {hi:g}]"
    if lo is not None:
        return f"a number >= {lo:g}"
    if hi is not None:
        return f"a number <= {hi:g}"
    return "a number"


def _check_number(where: str, v: Any, kind: str, lo, hi) -> float | int:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise _fail(where, v, f"expected {'an integer' if kind == 'int' else _range_text(lo, hi)}"
                    f"{'' if kind != 'int' else f' in [{lo}, {hi}]'}; write it without quotes")
    if kind == "int" and not (isinstance(v, int) or float(v).is_integer()):
        raise _fail(where, v, f"expected an integer in [{lo}, {hi}]")
    if not math.isfinite(float(v)):
        raise _fail(where, v, f"expected a finite value, {_range_text(lo, hi)}")
    if (lo is not None and v < lo) or (hi is not None and v > hi):
        raise _fail(where, v, f"outside the accepted range: expected {_range_text(lo, hi)}")
    return int(v) if kind == "int" else float(v)


def _check_field(sec: str, key: str, v: Any, spec: tuple) -> Any:
    kind, _default, lo, hi, _doc = spec
    where = f"{sec}.{key}"
    if kind in ("float", "int"):
        return _check_number(where, v, kind, lo, hi)
    if kind == "str":
        if not isinstance(v, str):
            raise _fail(where, v, "expected a string in quotes")
        return v
    if kind == "bool":
        if not isinstance(v, bool):
            raise _fail(where, v, "expected true or false")
        return v
    if kind.startswith("enum:"):
        choices = kind[5:].split("|")
        if v not in choices:
            raise _fail(where, v, f"expected one of {', '.join(repr(c) for c in choices)}")
        return v
    if kind == "range":
        if not isinstance(v, list) or len(v) != 2:
            raise _fail(where, v, f"expected a list of two numbers [low, high], each {_range_text(lo, hi)}")
        a = _check_number(where + "[0]", v[0], "float", lo, hi)
        b = _check_number(where + "[1]", v[1], "float", lo, hi)
        if not a < b:
            raise _fail(where, v, "expected low < high")
        return [a, b]
    raise AssertionError(kind)  # schema bug


#: sections that describe the drives off the line, not the drive the design and the firmware are made
#: for: they are left out of the profile's hash, so declaring tolerances (or naming one drive of a
#: tolerance study) keeps the profile's designs and firmware valid
UNHASHED_SECTIONS = ("tolerances", "as_built")


def _hash_raw(raw: dict) -> str:
    # Hash of the canonical resolved content, not the file bytes, so that
    # comments and formatting do not change the profile's identity.
    import json
    if isinstance(raw, dict):
        raw = {k: v for k, v in raw.items() if k not in UNHASHED_SECTIONS}
    return hashlib.sha256(json.dumps(raw, sort_keys=True, separators=(",", ":")).encode()).hexdigest()


def _build(raw: dict[str, Any], path: Path | None, sha: str) -> Profile:
    if not isinstance(raw, dict):
        raise ProfileError("profile must be a TOML table")
    schema = raw.get("schema", SCHEMA_ID)
    if schema != SCHEMA_ID:
        raise _fail("schema", schema, f"this picdrive reads {SCHEMA_ID!r}")
    unknown_sections = sorted(set(raw) - set(SCHEMA) - {"schema"} - set(UNHASHED_SECTIONS))
    if unknown_sections:
        raise ProfileError(
            f"profile has unknown section(s) {unknown_sections}; known sections are "
            f"{sorted(SCHEMA) + list(UNHASHED_SECTIONS)}")
    vals: dict[str, dict[str, Any]] = {}
    for sec, spec in SCHEMA.items():
        given = raw.get(sec, {})
        if not isinstance(given, dict):
            raise _fail(sec, given, f"expected a [{sec}] table")
        unknown = sorted(set(given) - set(spec))
        if unknown:
            import difflib
            hints = [f"{u!r} (did you mean {m[0]!r}?)" if (m := difflib.get_close_matches(u, spec, 1)) else repr(u)
                     for u in unknown]
            raise ProfileError(f"profile section [{sec}] has unknown field(s) {', '.join(hints)}; "
                               f"known fields: {', '.join(spec)}")
        out: dict[str, Any] = {}
        for key, fspec in spec.items():
            if key in given:
                out[key] = _check_field(sec, key, given[key], fspec)
            elif fspec[1] is REQUIRED:
                raise ProfileError(f"profile field '{sec}.{key}' is missing: {fspec[4]}"
                                   f"{'' if fspec[0] not in ('float', 'int') else ', ' + _range_text(fspec[2], fspec[3])}")
            else:
                out[key] = fspec[1]
        vals[sec] = out

    d, mo = vals["drive"], vals["motor"]
    if not _NAME_RE.match(d["name"]):
        raise _fail("drive.name", d["name"], "expected lowercase letters, digits, '_' or '-' (max 48 chars), starting with a letter or digit")

    # inductance: either inductance_h or both ld_h and lq_h
    if mo["inductance_h"] is not None:
        if mo["ld_h"] is not None or mo["lq_h"] is not None:
            raise ProfileError("profile fields 'motor.inductance_h' and 'motor.ld_h'/'motor.lq_h' are exclusive: "
                               "give inductance_h for a non-salient machine, or both ld_h and lq_h")
        mo["ld_h"] = mo["lq_h"] = mo["inductance_h"]
    elif mo["ld_h"] is None or mo["lq_h"] is None:
        raise ProfileError("profile field 'motor.inductance_h' is missing: give inductance_h, "
                           "or both ld_h and lq_h, in H, a number in [1e-07, 10]")
    del mo["inductance_h"]
    # EMF: flux linkage, or Kt/Kb
    if mo["flux_linkage_v_s"] is None and mo["torque_constant_n_m_per_a"] is None and mo["back_emf_constant_v_s"] is None:
        raise ProfileError("profile field 'motor.flux_linkage_v_s' is missing: give flux_linkage_v_s (V s/rad electrical), "
                           "or torque_constant_n_m_per_a and back_emf_constant_v_s")
    if mo["flux_linkage_v_s"] is not None and (mo["torque_constant_n_m_per_a"] is not None or mo["back_emf_constant_v_s"] is not None):
        raise ProfileError("profile fields 'motor.flux_linkage_v_s' and 'motor.torque_constant_n_m_per_a'/'back_emf_constant_v_s' "
                           "are exclusive: give one form of the EMF constant")

    kt, kb = mo["torque_constant_n_m_per_a"], mo["back_emf_constant_v_s"]
    if kt is not None and kb is not None and abs(kt / kb - 1.0) > KT_KB_TOLERANCE:
        raise ProfileError(
            f"profile fields 'motor.torque_constant_n_m_per_a' = {kt:g} and 'motor.back_emf_constant_v_s' = {kb:g} "
            f"differ by a factor {kt / kb:.4g}: in SI units they are the same constant (within "
            f"{100 * KT_KB_TOLERANCE:g} %); {_kt_kb_slip(kt / kb)}")

    inv, se, co, de = vals["inverter"], vals["sensors"], vals["control"], vals["design"]
    if se["hall_spacing_deg"] not in (60, 120):
        raise _fail("sensors.hall_spacing_deg", se["hall_spacing_deg"], "expected 60 or 120")
    if se["speed_source"] == "encoder" and se["encoder_lines"] == 0:
        raise _fail("sensors.speed_source", "encoder",
                    "no encoder is fitted (sensors.encoder_lines = 0): set encoder_lines or speed_source = \"hall\"")
    if inv["current_limit_a"] > inv["overcurrent_trip_a"]:
        raise _fail("inverter.current_limit_a", inv["current_limit_a"],
                    f"must not exceed inverter.overcurrent_trip_a = {inv['overcurrent_trip_a']:g} A")
    if inv["bus_voltage_v"] > inv["switch_vds_max_v"]:
        raise _fail("inverter.bus_voltage_v", inv["bus_voltage_v"],
                    f"exceeds the switch rating inverter.switch_vds_max_v = {inv['switch_vds_max_v']:g} V")
    if inv["brake_resistor_ohm"] > 0.0:
        if inv["brake_chopper_v"] == 0.0:
            inv["brake_chopper_v"] = 1.1 * inv["bus_voltage_v"]
        if inv["brake_chopper_v"] <= inv["bus_voltage_v"]:
            raise _fail("inverter.brake_chopper_v", inv["brake_chopper_v"],
                        f"must be above inverter.bus_voltage_v = {inv['bus_voltage_v']:g} V (at or below it the "
                        "resistor burns the supply's power); 0 takes 110 % of the bus")
        if inv["brake_chopper_v"] >= 0.9 * inv["switch_vds_max_v"]:
            raise _fail("inverter.brake_chopper_v", inv["brake_chopper_v"],
                        f"must be below 90 % of the switch rating ({0.9 * inv['switch_vds_max_v']:g} V of "
                        f"inverter.switch_vds_max_v = {inv['switch_vds_max_v']:g} V): the chopper must act before "
                        "the switches are at risk")
    elif inv["brake_chopper_v"] != 0.0:
        raise _fail("inverter.brake_chopper_v", inv["brake_chopper_v"],
                    "has no effect without inverter.brake_resistor_ohm: set the resistor too, or remove it")
    if inv["bus_sense_v_per_v"] > 0.0:
        ov_v = min(f * inv[k] for f, k in zip(BUS_GUARD_LEVELS["trip"], ("bus_voltage_v", "switch_vds_max_v")))
        if inv["bus_sense_v_per_v"] * ov_v >= 5.0:
            raise _fail("inverter.bus_sense_v_per_v", inv["bus_sense_v_per_v"],
                        f"puts the overvoltage trip ({ov_v:.1f} V) at {inv['bus_sense_v_per_v'] * ov_v:.2f} V on AN1, "
                        "beyond the ADC's 5 V: the firmware could not see it; a divider of at most "
                        f"{4.9 / ov_v:.4g} V/V")
    period_ns = 1e9 / inv["pwm_frequency_hz"]
    if inv["bootstrap_refresh_ns"] + 2 * inv["dead_time_ns"] >= 0.5 * period_ns:
        raise _fail("inverter.dead_time_ns", inv["dead_time_ns"],
                    f"dead time x2 plus bootstrap refresh ({inv['bootstrap_refresh_ns']:g} ns) leaves less than half "
                    f"of the {period_ns:g} ns PWM period: lower the PWM frequency or the dead time")
    if co["speed_min_rpm"] >= co["speed_max_rpm"]:
        raise _fail("control.speed_min_rpm", co["speed_min_rpm"],
                    f"must be below control.speed_max_rpm = {co['speed_max_rpm']:g}")
    if co["reference_rpm"] > co["speed_max_rpm"]:
        raise _fail("control.reference_rpm", co["reference_rpm"],
                    f"must not exceed control.speed_max_rpm = {co['speed_max_rpm']:g}")
    if co["speed_loop_hz"] > inv["pwm_frequency_hz"]:
        raise _fail("control.speed_loop_hz", co["speed_loop_hz"],
                    f"must not exceed inverter.pwm_frequency_hz = {inv['pwm_frequency_hz']:g}")
    p = Profile(
        name=d["name"], description=d["description"], source=d["source"],
        motor=Motor(**mo), inverter=Inverter(**inv), sensors=Sensors(**se),
        control=Control(**co), uart=Uart(**vals["uart"]), design=de,
        path=path, sha256=sha, raw=raw,
    )
    from .tolerances import ToleranceError, parse_as_built, parse_tolerances
    try:
        tol = parse_tolerances(raw.get("tolerances"), p)
        seed = parse_as_built(raw.get("as_built"))
    except ToleranceError as e:
        raise ProfileError(str(e)) from None
    p = dataclasses.replace(p, tolerances=tol, as_built_seed=seed)
    _check_simulation_size(p)
    reach = p.max_reachable_rpm()
    if co["speed_max_rpm"] > reach:
        warnings.warn(
            f"profile '{p.name}': control.speed_max_rpm = {co['speed_max_rpm']:g} rpm cannot be reached: "
            f"back-EMF (Kb = {p.motor.kb_v_s_per_rad:.4g} V s/rad) plus IR drop exceeds the usable bus voltage "
            f"{inv['bus_voltage_v']:g} V x max duty {p.max_duty():.3f}; the no-load limit is about {reach:.0f} rpm",
            ProfileWarning, stacklevel=3)
    return p


def loads_profile(text: str, path: Path | None = None) -> Profile:
    """Parse and validate a profile from TOML text."""
    try:
        raw = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        where = f"{path}: " if path else ""
        raise ProfileError(f"{where}not valid TOML: {e}") from None
    return _build(raw, path, _hash_raw(raw))


def load_profile(path: str | Path) -> Profile:
    """Load and validate a profile file (a path, or the name of a bundled profile)."""
    p = resolve_profile_path(path)
    text = read_input_text(p, "profile", limit_bytes=PROFILE_MAX_BYTES, error=ProfileError)
    try:
        return loads_profile(text, p)
    except ProfileError as e:
        if str(e).startswith(str(p)):
            raise
        raise ProfileError(f"{p}: {e}") from None


def examples_dir() -> Path:
    """Folder of the bundled example profiles (``examples/`` at the repository root)."""
    from .paths import repo_root
    return repo_root() / "examples"


def bundled_profiles() -> dict[str, Path]:
    """Bundled profiles by name."""
    return {p.stem: p for p in sorted(examples_dir().glob("*.toml"))}


def schema_markdown() -> str:
    """``docs/profile.md``: every profile field with its unit, default and range,
    generated from :data:`SCHEMA` (a test keeps the file current)."""
    lines = [
        "# Drive profile fields",
        "",
        "<!-- generated by picdrive.profile.schema_markdown(); do not edit by hand -->",
        "",
        "A drive profile is a TOML file (`schema = \"picdrive.profile/1\"`) with the sections below.",
        "Units are SI and are part of each field's name; speeds at the user interface are in rpm.",
        "Loading validates every field: a missing, non-numeric or out-of-range value is an error that",
        "names the field, the value and the accepted range.  Loading warns when the speed range cannot",
        "be reached on the bus voltage (back-EMF plus IR drop above the usable voltage).",
        "",
        "Exactly one inductance form (`inductance_h`, or both `ld_h` and `lq_h`) and one EMF form",
        "(`flux_linkage_v_s`, or `torque_constant_n_m_per_a` and `back_emf_constant_v_s`) must be given.",
        "In SI units the six-step Kt and Kb are one constant: a profile whose Kt / Kb is off 1 by more than",
        f"{100 * KT_KB_TOLERANCE:g} % is refused, naming the likely unit slip (Kt in mN m/A, Kb in V/krpm, a phase",
        "value...).  Within it, every model (design, verification, firmware, twin) uses Kb for both.",
        "",
        "Plausibility before computation: the design's verification simulates a step from rest and a load",
        f"step, each {VERIFY_PHASE_PER_MIN_STEP:g} times the drive's fastest step from rest at its current limit",
        "(t_min = J w / (Kt I_lim - T_load)), one integration step per PWM period.  A profile whose figures",
        f"need more than {VERIFY_MAX_PWM_PERIODS:g} PWM periods for it (the bundled drives need 24 000) is refused",
        "before any computation, naming the inertia, t_min, the mechanical time constant J R / (Kt Kb), the",
        "simulation's length and memory, and the likely unit slip (J in kg cm^2 or g cm^2 typed as kg m^2).",
        "",
        f"A profile file is read only if it is a regular file of at most {PROFILE_MAX_BYTES // 1024} KiB of UTF-8 text:",
        "a FIFO, a device (`/dev/zero`) or a folder is refused before it is opened.",
        "",
        "Two optional sections describe the drives off the line rather than the drive the design and the",
        "firmware are made for, and are left out of the profile's hash (declaring them keeps the profile's",
        "designs and firmware valid): `[tolerances]`, the production spread of each parameter that",
        "`picdrive robustness` draws from, and `[as_built]`, one drive of such a study named by its `seed`,",
        "which `picdrive twin` runs.  Their fields, distributions and defaults: `docs/robustness.md`.",
        "",
    ]
    for sec, spec in SCHEMA.items():
        lines += [f"## [{sec}]", "", "| field | kind | default | accepted | meaning |", "|---|---|---|---|---|"]
        for key, (kind, default, lo, hi, doc) in spec.items():
            dflt = "**required**" if default is REQUIRED else ("—" if default is None else f"`{default!r}`".replace("'", '"'))
            if kind.startswith("enum:"):
                acc, kind = " \\| ".join(f"`{c}`" for c in kind[5:].split("|")), "choice"
            elif lo is not None or hi is not None:
                acc = f"[{lo:g}, {hi:g}]" if lo is not None and hi is not None else (f">= {lo:g}" if lo is not None else f"<= {hi:g}")
            else:
                acc = ""
            lines.append(f"| `{key}` | {kind} | {dflt} | {acc} | {doc} |")
        lines.append("")
    return "\n".join(lines)


def resolve_profile_path(path: str | Path) -> Path:
    p = Path(path)
    if p.exists():
        return p
    b = bundled_profiles()
    if str(path) in b:
        return b[str(path)]
    raise ProfileError(f"no profile file {str(path)!r}; give a path to a .toml file or one of the bundled "
                       f"profiles: {', '.join(b) or '(none found)'}")
