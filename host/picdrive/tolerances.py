"""Production tolerances of a drive: how far each motor off the line differs from the profile.

A profile's ``[tolerances]`` section declares, per parameter, the distribution
of its deviation from the nominal value; ``picdrive robustness`` draws one
drive per sample from it and runs the design's verification scenario on that
drive (the firmware is the nominal one: it was built from the profile's
nominal numbers, as it is flashed on every drive of the line).  A profile's
``[as_built]`` section names one such drive by its seed: the motor twin
(``picdrive twin``) draws the same deviations from the same seed and runs that
drive.

Parameters (:data:`PARAMETERS`): ``resistance``, ``back_emf`` (Ke = Kt, the
magnet's flux), ``inductance``, ``inertia``, ``friction``, ``bus_voltage`` and
``load_torque`` deviate by a percentage of the nominal value (``*_pct``
fields, the drive's value is nominal x (1 + x / 100)); ``hall_offset`` by
electrical degrees (``*_deg`` fields, added to ``sensors.hall_offset_deg`` in
the motor only: the firmware's commutation table stays the nominal one).

Distributions:

* ``uniform`` -- ``low_pct``, ``high_pct`` (or ``_deg``): every value between
  equally likely (a datasheet's "+-10 %" with nothing known inside it);
* ``truncated-normal`` -- ``sigma_pct``, optional ``mean_pct`` (0) and the
  truncation ``low_pct``, ``high_pct`` (default +-3 sigma around the mean): a
  production spread centred on the nominal, screened at the limits;
* ``none`` -- the parameter is the nominal one.

A parameter the section does not name takes its default (:data:`DEFAULTS`,
from typical datasheets; ``docs/robustness.md`` gives the sources); a profile
without the section takes every default.

Drawing is deterministic: sample ``k`` of a study seeded ``S`` has the seed
:func:`sample_seed` ``(S, k)``; each parameter draws from its own stream
(``numpy.random.default_rng([seed, code])``), so widening one parameter's
tolerance leaves every other parameter's draws unchanged.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np

from .errors import PicdriveError

__all__ = ["ToleranceError", "Tolerance", "Deviation", "PARAMETERS", "DEFAULTS", "DISTRIBUTIONS",
           "parse_tolerances", "parse_as_built", "sample_seed", "draw", "describe", "nominal_value",
           "tolerances_toml"]


class ToleranceError(PicdriveError, ValueError):
    """A ``[tolerances]`` or ``[as_built]`` entry is not valid; the message names the field and the fix."""


# name -> (unit of its fields, what it multiplies or shifts, the profile field, lowest factor allowed,
#          stream code, the twin plant's perturbation key or None)
PARAMETERS: dict[str, dict[str, Any]] = {
    "resistance": {"unit": "pct", "field": "motor.resistance_ohm", "what": "winding resistance R",
                   "code": 1, "perturb": "resistance", "zero_ok": False},
    "back_emf": {"unit": "pct", "field": "motor.back_emf_constant_v_s", "what": "back-EMF constant Ke (= Kt)",
                 "code": 2, "perturb": "flux", "zero_ok": False},
    "inductance": {"unit": "pct", "field": "motor.inductance_h", "what": "winding inductance L",
                   "code": 3, "perturb": "inductance", "zero_ok": False},
    "inertia": {"unit": "pct", "field": "motor.inertia_kg_m2", "what": "rotor + load inertia J",
                "code": 4, "perturb": "inertia", "zero_ok": False},
    "friction": {"unit": "pct", "field": "motor.viscous_friction_n_m_s", "what": "viscous friction B",
                 "code": 5, "perturb": "friction", "zero_ok": True},
    "hall_offset": {"unit": "deg", "field": "sensors.hall_offset_deg", "what": "hall sensor placement",
                    "code": 6, "perturb": None, "zero_ok": True},
    "bus_voltage": {"unit": "pct", "field": "inverter.bus_voltage_v", "what": "DC bus voltage",
                    "code": 7, "perturb": "bus_voltage", "zero_ok": False},
    "load_torque": {"unit": "pct", "field": "control.load_torque_n_m", "what": "load-torque step",
                    "code": 8, "perturb": None, "zero_ok": True},
}

DISTRIBUTIONS = ("uniform", "truncated-normal", "none")

#: the twin's plant takes factors in this range (picdrive_hil.plant.parse_perturb)
FACTOR_RANGE = (0.1, 10.0)

#: Defaults from typical datasheets, each with the reason (docs/robustness.md repeats them).
DEFAULTS: dict[str, dict[str, Any]] = {
    "resistance": {"distribution": "uniform", "low": -10.0, "high": 10.0,
                   "why": "winding resistance +-10 % at 25 C on small-BLDC datasheets (wire gauge and "
                          "winding); the verification's own R corners"},
    "back_emf": {"distribution": "truncated-normal", "mean": 0.0, "sigma": 2.5, "low": -7.0, "high": 7.0,
                 "why": "Ke / Kt +-5 .. 7 % on datasheets (magnet remanence and air gap), a production "
                        "spread of 2.5 % screened at +-7 %"},
    "inductance": {"distribution": "uniform", "low": -20.0, "high": 20.0,
                   "why": "winding inductance +-20 % on datasheets (often given as typical only)"},
    "inertia": {"distribution": "uniform", "low": 0.0, "high": 30.0,
                "why": "rotor inertia plus the coupled load: the application's range, nominal up to +30 %"},
    "friction": {"distribution": "uniform", "low": -20.0, "high": 20.0,
                 "why": "bearing and seal friction +-20 % with temperature and run-in"},
    "hall_offset": {"distribution": "truncated-normal", "mean": 0.0, "sigma": 1.0, "low": -3.0, "high": 3.0,
                    "why": "hall sensors placed within a few electrical degrees (PCB and magnet tolerances), "
                           "1 degree spread screened at +-3 degrees"},
    "bus_voltage": {"distribution": "uniform", "low": -5.0, "high": 5.0,
                    "why": "a regulated supply's +-5 %; a battery or an unregulated bus needs +-10 % or more: "
                           "declare it"},
    "load_torque": {"distribution": "uniform", "low": -10.0, "high": 10.0,
                    "why": "the application's load step +-10 %"},
}


@dataclass(frozen=True)
class Tolerance:
    """One parameter's distribution: deviations in % of nominal (``unit == "pct"``) or electrical
    degrees (``"deg"``).  ``low``/``high`` bound every draw; ``mean``/``sigma`` only for
    ``truncated-normal``."""

    name: str
    distribution: str
    low: float = 0.0
    high: float = 0.0
    mean: float = 0.0
    sigma: float = 0.0
    declared: bool = False           # named in the profile (else a default)

    @property
    def unit(self) -> str:
        return PARAMETERS[self.name]["unit"]

    def text(self) -> str:
        """One line: ``uniform -10 .. +10 %``."""
        u = "%" if self.unit == "pct" else "deg (electrical)"
        if self.distribution == "none":
            return "none (nominal)"
        if self.distribution == "uniform":
            return f"uniform {self.low:+g} .. {self.high:+g} {u}"
        return f"truncated normal, mean {self.mean:+g}, sigma {self.sigma:g}, within {self.low:+g} .. {self.high:+g} {u}"

    def draw(self, rng: np.random.Generator) -> float:
        """One deviation (% or deg) drawn with ``rng`` (one uniform number per draw, whatever the
        distribution: the stream stays aligned)."""
        u = float(rng.random())
        if self.distribution == "none":
            return 0.0
        if self.distribution == "uniform":
            return self.low + (self.high - self.low) * u
        from scipy.special import ndtr, ndtri
        a, b = ndtr((self.low - self.mean) / self.sigma), ndtr((self.high - self.mean) / self.sigma)
        x = self.mean + self.sigma * float(ndtri(a + (b - a) * u))
        return min(max(x, self.low), self.high)


@dataclass(frozen=True)
class Deviation:
    """One drive off the line: the factor on each multiplied parameter, the hall error, its seed.

    ``factors``: parameter name -> factor (1.05 = +5 %) for the percentage parameters;
    ``hall_error_deg``: electrical degrees added to the motor's hall placement."""

    seed: int
    factors: Mapping[str, float]
    hall_error_deg: float

    def plant_perturb(self) -> dict[str, float]:
        """The twin plant's perturbations (``picdrive_hil.plant.PERTURB_KEYS``): the factors that
        act on the motor and the bus."""
        return {PARAMETERS[k]["perturb"]: v for k, v in self.factors.items() if PARAMETERS[k]["perturb"]}

    @property
    def load_factor(self) -> float:
        """Factor on the scenario's load-torque step."""
        return float(self.factors.get("load_torque", 1.0))

    def values(self) -> dict[str, float]:
        """Each parameter's deviation: % for the multiplied ones, degrees for the hall offset."""
        out = {k: 100.0 * (f - 1.0) for k, f in self.factors.items()}
        out["hall_offset"] = self.hall_error_deg
        return {k: out[k] for k in PARAMETERS}

    def text(self) -> str:
        """``R +3.1 %, Ke -1.2 %, ...``, every parameter."""
        short = {"resistance": "R", "back_emf": "Ke", "inductance": "L", "inertia": "J", "friction": "B",
                 "hall_offset": "hall", "bus_voltage": "bus", "load_torque": "load"}
        return ", ".join(f"{short[k]} {v:+.2f} {'deg' if PARAMETERS[k]['unit'] == 'deg' else '%'}"
                         for k, v in self.values().items())


def _where(name: str, key: str | None = None) -> str:
    return f"tolerances.{name}" + (f".{key}" if key else "")


def _num(name: str, key: str, v: Any) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(float(v)):
        raise ToleranceError(f"profile field '{_where(name, key)}' = {v!r}: expected a finite number, "
                             "written without quotes")
    return float(v)


def nominal_value(profile, name: str) -> float:
    """The profile's nominal value of a parameter, SI units (degrees for the hall offset)."""
    m, inv = profile.motor, profile.inverter
    return {"resistance": m.resistance_ohm, "back_emf": m.kb_v_s_per_rad, "inductance": 0.5 * (m.ld_h + m.lq_h),
            "inertia": m.inertia_kg_m2, "friction": m.viscous_friction_n_m_s,
            "hall_offset": profile.sensors.hall_offset_deg, "bus_voltage": inv.bus_voltage_v,
            "load_torque": profile.control.load_torque_n_m}[name]


def _one(name: str, given: Any, nominal: float | None) -> Tolerance:
    unit = PARAMETERS[name]["unit"]
    other = "deg" if unit == "pct" else "pct"
    if not isinstance(given, dict):
        raise ToleranceError(f"profile field '{_where(name)}' = {given!r}: expected a table, e.g. "
                             f"{name} = {{ distribution = \"uniform\", low_{unit} = -10, high_{unit} = 10 }}")
    dist = given.get("distribution")
    if dist not in DISTRIBUTIONS:
        raise ToleranceError(f"profile field '{_where(name, 'distribution')}' = {dist!r}: the distributions "
                             f"known are {', '.join(repr(d) for d in DISTRIBUTIONS)}")
    allowed = {"distribution"} | ({"low", "high"} if dist == "uniform" else set()) | \
        ({"low", "high", "mean", "sigma"} if dist == "truncated-normal" else set())
    vals: dict[str, float] = {}
    for key, v in given.items():
        if key == "distribution":
            continue
        base, _, suffix = key.rpartition("_")
        if suffix == other and base in allowed:
            raise ToleranceError(f"profile field '{_where(name, key)}': {name} deviates in "
                                 f"{'percent of nominal' if unit == 'pct' else 'electrical degrees'}; write "
                                 f"{base}_{unit}")
        if suffix != unit or base not in allowed:
            known = ", ".join(f"{k}_{unit}" for k in sorted(allowed - {"distribution"})) or "no other field"
            raise ToleranceError(f"profile field '{_where(name, key)}' is not a field of a {dist} tolerance; "
                                 f"it takes {known}")
        vals[base] = _num(name, key, v)
    if dist == "none":
        return Tolerance(name, "none", declared=True)
    if dist == "uniform":
        for k in ("low", "high"):
            if k not in vals:
                raise ToleranceError(f"profile field '{_where(name, k + '_' + unit)}' is missing: a uniform "
                                     f"tolerance takes low_{unit} and high_{unit}")
        if not vals["low"] <= vals["high"]:
            raise ToleranceError(f"profile field '{_where(name)}': low_{unit} = {vals['low']:g} is above "
                                 f"high_{unit} = {vals['high']:g}; swap them")
        tol = Tolerance(name, dist, vals["low"], vals["high"], declared=True)
    else:
        if "sigma" not in vals:
            raise ToleranceError(f"profile field '{_where(name, 'sigma_' + unit)}' is missing: a truncated-normal "
                                 f"tolerance takes sigma_{unit} (and optionally mean_{unit}, low_{unit}, high_{unit})")
        if not vals["sigma"] > 0:
            raise ToleranceError(f"profile field '{_where(name, 'sigma_' + unit)}' = {vals['sigma']:g}: expected "
                                 f"a number > 0 (or distribution = \"none\" for the nominal value)")
        mean = vals.get("mean", 0.0)
        low, high = vals.get("low", mean - 3 * vals["sigma"]), vals.get("high", mean + 3 * vals["sigma"])
        if not low < high:
            raise ToleranceError(f"profile field '{_where(name)}': low_{unit} = {low:g} is not below "
                                 f"high_{unit} = {high:g}")
        if not low <= mean <= high:
            raise ToleranceError(f"profile field '{_where(name, 'mean_' + unit)}' = {mean:g} lies outside its "
                                 f"truncation {low:g} .. {high:g}")
        tol = Tolerance(name, dist, low, high, mean, vals["sigma"], declared=True)
    _check_range(tol, nominal)
    return tol


def _check_range(tol: Tolerance, nominal: float | None) -> None:
    """Every draw keeps the parameter physical: positive (>= 0 for friction and load) and within the
    twin's factor range."""
    name, unit = tol.name, tol.unit
    if unit == "deg":
        if tol.low < -60 or tol.high > 60:
            raise ToleranceError(f"profile field '{_where(name)}': {tol.low:g} .. {tol.high:g} electrical degrees "
                                 "moves a hall edge by a whole sector or more (60 degrees); a placement tolerance "
                                 "is a few degrees")
        return
    zero_ok = PARAMETERS[name]["zero_ok"]
    f_low, f_high = 1 + tol.low / 100.0, 1 + tol.high / 100.0
    if f_low < 0 or (f_low == 0 and not zero_ok) or (not zero_ok and f_low < FACTOR_RANGE[0]):
        at = "" if nominal is None else f": {nominal:g} x (1 {tol.low:+g} %) = {nominal * f_low:.4g}"
        need = ">= -100" if zero_ok else f">= {100 * (FACTOR_RANGE[0] - 1):g}"
        raise ToleranceError(f"profile field '{_where(name, 'low_pct')}' = {tol.low:g} makes the "
                             f"{PARAMETERS[name]['what']} {'negative' if f_low < 0 else 'non-positive or too small'}"
                             f"{at} ({PARAMETERS[name]['field']}); the lowest deviation must be {need} %")
    if f_high > FACTOR_RANGE[1]:
        raise ToleranceError(f"profile field '{_where(name, 'high_pct')}' = {tol.high:g}: the twin takes at most "
                             f"{FACTOR_RANGE[1]:g} x the nominal value ({100 * (FACTOR_RANGE[1] - 1):g} %)")


def _default(name: str) -> Tolerance:
    d = DEFAULTS[name]
    return Tolerance(name, d["distribution"], d.get("low", 0.0), d.get("high", 0.0), d.get("mean", 0.0),
                     d.get("sigma", 0.0), declared=False)


def parse_tolerances(section: Any, profile=None) -> dict[str, Tolerance]:
    """The ``[tolerances]`` section (a dict, or None for none) -> every parameter's :class:`Tolerance`
    (defaults filled in).  Raises :class:`ToleranceError` naming the field and the fix."""
    if section is None:
        section = {}
    if not isinstance(section, dict):
        raise ToleranceError(f"profile field 'tolerances' = {section!r}: expected a [tolerances] table")
    unknown = sorted(set(section) - set(PARAMETERS))
    if unknown:
        import difflib
        hints = [f"{u!r} (did you mean {m[0]!r}?)" if (m := difflib.get_close_matches(u, PARAMETERS, 1)) else repr(u)
                 for u in unknown]
        raise ToleranceError(f"profile section [tolerances] has unknown parameter(s) {', '.join(hints)}; known: "
                             f"{', '.join(PARAMETERS)}")
    out = {}
    for name in PARAMETERS:
        nominal = nominal_value(profile, name) if profile is not None else None
        out[name] = _one(name, section[name], nominal) if name in section else _default(name)
    return out


def parse_as_built(section: Any) -> int | None:
    """The ``[as_built]`` section -> the drive's seed (None without the section)."""
    if section is None:
        return None
    if not isinstance(section, dict):
        raise ToleranceError(f"profile field 'as_built' = {section!r}: expected an [as_built] table with seed = N")
    unknown = sorted(set(section) - {"seed", "study_seed", "sample"})
    if unknown:
        raise ToleranceError(f"profile section [as_built] has unknown field(s) {unknown}; it takes seed (and "
                             "study_seed, sample: where the drive came from)")
    if "seed" not in section:
        raise ToleranceError("profile field 'as_built.seed' is missing: the seed the drive's deviations are "
                             "drawn from (picdrive robustness writes it)")
    for k in ("seed", "study_seed", "sample"):
        v = section.get(k, 0)
        if isinstance(v, bool) or not isinstance(v, int) or not 0 <= v <= 2**31 - 1:
            raise ToleranceError(f"profile field 'as_built.{k}' = {v!r}: expected an integer in [0, 2147483647]")
    return int(section["seed"])


def sample_seed(study_seed: int, index: int) -> int:
    """The seed of sample ``index`` of a study seeded ``study_seed`` (in [0, 2^31 - 1])."""
    state = np.random.SeedSequence([int(study_seed), int(index)]).generate_state(1, dtype=np.uint32)[0]
    return int(state) & 0x7FFFFFFF


def draw(tolerances: Mapping[str, Tolerance], seed: int) -> Deviation:
    """The drive of a seed: each parameter's deviation from its own stream (see the module docstring)."""
    factors, hall = {}, 0.0
    for name, tol in tolerances.items():
        x = tol.draw(np.random.default_rng([int(seed), PARAMETERS[name]["code"]]))
        if tol.unit == "deg":
            hall = x
        else:
            factors[name] = 1.0 + x / 100.0
    return Deviation(int(seed), factors, hall)


def describe(tolerances: Mapping[str, Tolerance]) -> list[str]:
    """One line per parameter: name, distribution, and whether it is the default."""
    return [f"{name:12s} {tol.text()}" + ("" if tol.declared else "  (default)") for name, tol in tolerances.items()]


def tolerances_toml(tolerances: Mapping[str, Tolerance]) -> str:
    """The ``[tolerances]`` section that declares ``tolerances`` (every parameter, defaults included)."""
    lines = ["[tolerances]"]
    for name, t in tolerances.items():
        u = t.unit
        if t.distribution == "none":
            body = 'distribution = "none"'
        elif t.distribution == "uniform":
            body = f'distribution = "uniform", low_{u} = {t.low!r}, high_{u} = {t.high!r}'
        else:
            body = (f'distribution = "truncated-normal", mean_{u} = {t.mean!r}, sigma_{u} = {t.sigma!r}, '
                    f'low_{u} = {t.low!r}, high_{u} = {t.high!r}')
        lines.append(f"{name} = {{ {body} }}")
    return "\n".join(lines) + "\n"
