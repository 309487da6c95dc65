"""Plant parameters of the twin from a drive profile, with perturbations.

The twin's plant is a per-phase model of the wye winding (docs/twin.md), so
it takes the profile's *derived* per-phase quantities (architecture.md,
seam 1): ``r_phase_ohm``, ``(ld_phase_h + lq_phase_h) / 2``,
``lambda_m_v_s``, ``pole_pairs``, ``back_emf_shape``.  With those, the
six-step DC equivalent of the plant has exactly the profile's
``kb_v_s_per_rad``/``kt_n_m_per_a`` and ``r_line_ohm``/``l_line_h``.

Perturbations multiply a parameter: ``{"resistance": 1.1}`` is R + 10 %
(the 2016 paper's uncertainty).  Keys: resistance, inductance, flux,
inertia, friction, bus_voltage.
"""
from __future__ import annotations

import ctypes as C
import math
from dataclasses import dataclass, field, replace
from typing import Mapping

from picdrive.errors import PicdriveError

from . import cmodel

PERTURB_KEYS = {
    "resistance": "r_phase_ohm",
    "inductance": "l_phase_h",
    "flux": "lambda_m_v_s",
    "inertia": "inertia_kg_m2",
    "friction": "friction_n_m_s",
    "bus_voltage": "bus_voltage_v",
}
LOAD_MODES = {"active": cmodel.LOAD_ACTIVE, "passive": cmodel.LOAD_PASSIVE}


class PlantError(PicdriveError, ValueError):
    """A plant perturbation or option is not valid."""


@dataclass(frozen=True)
class PlantModel:
    """Parameters of the twin's BLDC plant (SI units, per phase)."""

    r_phase_ohm: float
    l_phase_h: float
    lambda_m_v_s: float
    pole_pairs: int
    emf_shape: str                 # "trapezoidal" | "sinusoidal"
    inertia_kg_m2: float
    friction_n_m_s: float
    bus_voltage_v: float
    hall_offset_deg: float = 0.0
    hall_spacing_deg: float = 120.0
    encoder_lines: int = 0
    load_mode: str = "passive"
    diode_drop_v: float = 0.0
    bus_capacitance_f: float = 0.0         # 0: a stiff bus
    supply_sink_a: float = 0.0
    brake_resistor_ohm: float = 0.0        # 0: none
    brake_chopper_v: float = 0.0
    perturb: Mapping[str, float] = field(default_factory=dict)

    # -- six-step DC equivalents (for limits and checks) --------------------
    @property
    def dc_factor(self) -> float:
        return 2.0 if self.emf_shape == "trapezoidal" else 3.0 * math.sqrt(3.0) / math.pi

    @property
    def kb_v_s_per_rad(self) -> float:
        return self.dc_factor * self.pole_pairs * self.lambda_m_v_s

    @property
    def kt_n_m_per_a(self) -> float:
        # two phases carry the line current; at the flat tops T = 2 P lambda_m i
        return self.kb_v_s_per_rad

    @property
    def r_line_ohm(self) -> float:
        return 2.0 * self.r_phase_ohm

    def to_c(self) -> cmodel.PlantParams:
        return cmodel.PlantParams(
            r_phase_ohm=self.r_phase_ohm, l_phase_h=self.l_phase_h,
            lambda_m_v_s=self.lambda_m_v_s, pole_pairs=self.pole_pairs,
            emf_shape=cmodel.EMF_SINUSOIDAL if self.emf_shape == "sinusoidal" else cmodel.EMF_TRAPEZOIDAL,
            inertia_kg_m2=self.inertia_kg_m2, friction_n_m_s=self.friction_n_m_s,
            bus_voltage_v=self.bus_voltage_v, diode_drop_v=self.diode_drop_v,
            hall_offset_rad=math.radians(self.hall_offset_deg),
            hall_spacing_rad=math.radians(self.hall_spacing_deg),
            encoder_lines=self.encoder_lines, load_mode=LOAD_MODES[self.load_mode],
            bus_capacitance_f=self.bus_capacitance_f, supply_sink_a=self.supply_sink_a,
            brake_resistor_ohm=self.brake_resistor_ohm, brake_chopper_v=self.brake_chopper_v)

    def with_(self, **kw) -> "PlantModel":
        return replace(self, **kw)


def parse_perturb(items, profile=None) -> dict[str, float]:
    """``["resistance=1.1", ...]`` or a mapping -> validated ``{key: factor}``.

    ``resistance=+u`` / ``resistance=-u``: R x (1 +- the profile's
    ``design.resistance_uncertainty``), the 2016 paper's +-10 % (needs ``profile``)."""
    if items is None:
        return {}
    if isinstance(items, Mapping):
        pairs = list(items.items())
    else:
        pairs = []
        for it in items:
            if "=" not in str(it):
                raise PlantError(f"perturbation {it!r}: expected KEY=FACTOR, e.g. resistance=1.1 (R + 10 %)")
            k, v = str(it).split("=", 1)
            v = v.strip()
            if k.strip() == "resistance" and v in ("+u", "-u"):
                if profile is None:
                    raise PlantError(f"perturbation {it!r}: +u/-u need the profile's design.resistance_uncertainty")
                u = float(profile.design["resistance_uncertainty"])
                pairs.append(("resistance", 1.0 + u if v == "+u" else 1.0 - u))
                continue
            try:
                pairs.append((k.strip(), float(v)))
            except ValueError:
                raise PlantError(f"perturbation {it!r}: FACTOR must be a number, e.g. resistance=1.1, "
                                 "or resistance=+u / -u for the profile's resistance_uncertainty") from None
    out: dict[str, float] = {}
    for k, v in pairs:
        if k not in PERTURB_KEYS:
            raise PlantError(f"unknown perturbation {k!r}; known: {', '.join(PERTURB_KEYS)}")
        v = float(v)
        if not (math.isfinite(v) and 0.1 <= v <= 10.0):
            raise PlantError(f"perturbation {k}={v!r}: the factor must be in [0.1, 10] (1.1 = +10 %)")
        out[k] = v
    return out


def plant_from_profile(profile, perturb=None, *, load_mode: str = "passive",
                       diode_drop_v: float = 0.0, hall_error_deg: float = 0.0) -> PlantModel:
    """The twin plant of a profile, with multiplicative perturbations applied.

    ``hall_error_deg``: electrical degrees added to the hall sensors' placement in the motor only
    (the firmware's commutation table is built from the profile's ``sensors.hall_offset_deg``)."""
    if not (math.isfinite(hall_error_deg) and -60.0 <= hall_error_deg <= 60.0):
        raise PlantError(f"hall placement error {hall_error_deg!r} deg: expected -60 .. 60 electrical degrees")
    if load_mode not in LOAD_MODES:
        raise PlantError(f"load mode {load_mode!r}: choose 'active' (signed torque, 2016 eq 5) "
                         "or 'passive' (opposes motion, holds a standing rotor)")
    if not (0.0 <= diode_drop_v < 5.0):
        raise PlantError(f"diode drop {diode_drop_v!r} V: expected 0 .. 5 V")
    pert = parse_perturb(perturb, profile)
    m, inv, se = profile.motor, profile.inverter, profile.sensors
    base = dict(
        r_phase_ohm=m.r_phase_ohm,
        l_phase_h=0.5 * (m.ld_phase_h + m.lq_phase_h),
        lambda_m_v_s=m.lambda_m_v_s,
        inertia_kg_m2=m.inertia_kg_m2,
        friction_n_m_s=m.viscous_friction_n_m_s,
        bus_voltage_v=inv.bus_voltage_v,
    )
    for k, f in pert.items():
        base[PERTURB_KEYS[k]] *= f
    return PlantModel(pole_pairs=m.pole_pairs, emf_shape=m.back_emf_shape,
                      hall_offset_deg=se.hall_offset_deg + hall_error_deg, hall_spacing_deg=float(se.hall_spacing_deg),
                      encoder_lines=se.encoder_lines, load_mode=load_mode,
                      diode_drop_v=diode_drop_v, perturb=pert, bus_capacitance_f=inv.bus_capacitance_f,
                      supply_sink_a=inv.supply_sink_a, brake_resistor_ohm=inv.brake_resistor_ohm,
                      brake_chopper_v=inv.brake_chopper_v, **base)


class CPlant:
    """The compiled plant alone, stepped from Python (for cross-checks)."""

    def __init__(self, model: PlantModel):
        from .build import plant_library
        self._lib = cmodel.bind_plant(C.CDLL(str(plant_library())))
        for i, st in enumerate((cmodel.PlantParams, cmodel.PlantState, cmodel.Leg)):
            if self._lib.plant_sizeof(i) != C.sizeof(st):
                raise RuntimeError(f"ctypes mirror {st.__name__} ({C.sizeof(st)} B) differs from the C struct "
                                   f"({self._lib.plant_sizeof(i)} B): update cmodel.py")
        self.model = model
        self.params = model.to_c()
        self.state = cmodel.PlantState()
        self._lib.plant_reset(C.byref(self.state))
        self.state.v_bus_v = self.params.bus_voltage_v      # the capacitor charged to the supply
        self._legs = (cmodel.Leg * 3)()

    def step(self, legs, load_n_m: float, h_s: float) -> None:
        """Advance h_s with legs = [(f_hi, f_lo)] * 3 held over the step."""
        for k, (fh, fl) in enumerate(legs):
            self._legs[k].f_hi = fh
            self._legs[k].f_lo = fl
        self._lib.plant_step(C.byref(self.params), C.byref(self.state), self._legs, load_n_m, h_s)

    def hall_code(self, theta_mech: float | None = None) -> int:
        th = self.state.theta_rad if theta_mech is None else theta_mech
        return self._lib.plant_hall_code(C.byref(self.params), th)

    def emf_shape(self, theta_e: float) -> float:
        return self._lib.plant_emf_shape(C.byref(self.params), theta_e)
