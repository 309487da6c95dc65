"""A profile's production tolerances and the drives drawn from them (picdrive.tolerances), and the
study's statistics (picdrive.robustness.stats).  No twin runs here."""
from __future__ import annotations

import math
import warnings
from pathlib import Path

import numpy as np
import pytest

from picdrive.profile import ProfileError, load_profile, loads_profile
from picdrive.robustness.stats import failure_drivers, wilson_interval
from picdrive.tolerances import DEFAULTS, PARAMETERS, draw, sample_seed

ROOT = Path(__file__).resolve().parents[1]
BASE = (ROOT / "examples" / "duy2008.toml").read_text(encoding="utf-8")


def _load(extra: str):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return loads_profile(BASE + "\n" + extra)


def test_defaults_and_hash_unchanged():
    nominal = load_profile("duy2008")
    assert set(nominal.tolerances) == set(PARAMETERS) == set(DEFAULTS)
    assert not any(t.declared for t in nominal.tolerances.values())
    p = _load("[tolerances]\nresistance = { distribution = \"uniform\", low_pct = -30, high_pct = 30 }\n"
              "[as_built]\nseed = 7\n")
    # the sections describe drives off the line: the design and the firmware stay valid
    assert p.sha256 == nominal.sha256
    assert p.tolerances["resistance"].declared and (p.tolerances["resistance"].low, p.tolerances["resistance"].high) \
        == (-30.0, 30.0)
    assert p.as_built_seed == 7


def test_draw_is_deterministic_and_per_parameter():
    p = load_profile("duy2008")
    a, b = draw(p.tolerances, sample_seed(1, 5)), draw(p.tolerances, sample_seed(1, 5))
    assert a == b and sample_seed(1, 5) != sample_seed(1, 6) != sample_seed(2, 5)
    wide = _load("[tolerances]\nresistance = { distribution = \"uniform\", low_pct = -40, high_pct = 40 }\n")
    c = draw(wide.tolerances, sample_seed(1, 5))
    # widening one parameter leaves the others' draws as they were
    assert {k: v for k, v in c.factors.items() if k != "resistance"} == \
        {k: v for k, v in a.factors.items() if k != "resistance"} and c.hall_error_deg == a.hall_error_deg
    devs = np.array([draw(p.tolerances, sample_seed(3, k)).values()["back_emf"] for k in range(400)])
    assert devs.min() >= -7 and devs.max() <= 7 and 1.8 < devs.std() < 3.0       # sigma 2.5 %, screened at 7 %


@pytest.mark.parametrize("section, words", [
    ("resistance = { distribution = \"uniform\", low_pct = -120, high_pct = 10 }",
     ["tolerances.resistance.low_pct", "-120", "negative", "motor.resistance_ohm"]),
    ("inertia = { distribution = \"truncated-normal\", sigma_pct = 50, low_pct = -100 }",
     ["tolerances.inertia.low_pct", "non-positive"]),
    ("back_emf = { distribution = \"lognormal\", sigma_pct = 5 }",
     ["tolerances.back_emf.distribution", "'lognormal'", "'uniform'", "'truncated-normal'"]),
    ("resistence = { distribution = \"uniform\", low_pct = -10, high_pct = 10 }",
     ["unknown parameter", "did you mean 'resistance'"]),
    ("hall_offset = { distribution = \"uniform\", low_pct = -3, high_pct = 3 }",
     ["tolerances.hall_offset.low_pct", "electrical degrees", "low_deg"]),
    ("bus_voltage = { distribution = \"uniform\", low_pct = 10, high_pct = -10 }", ["swap them"]),
    ("friction = { distribution = \"truncated-normal\", low_pct = -5 }", ["sigma_pct", "is missing"]),
    ("load_torque = 10", ["tolerances.load_torque", "expected a table"]),
])
def test_bad_tolerances_name_the_field(section, words):
    with pytest.raises(ProfileError) as e:
        _load("[tolerances]\n" + section + "\n")
    for w in words:
        assert w in str(e.value), (w, str(e.value))


def test_bad_as_built():
    with pytest.raises(ProfileError, match="as_built.seed"):
        _load("[as_built]\nstudy_seed = 3\n")
    with pytest.raises(ProfileError, match="as_built.seed"):
        _load("[as_built]\nseed = -1\n")


def test_wilson_interval():
    lo, hi = wilson_interval(0, 10)
    assert lo == 0.0 and hi == pytest.approx(0.2775, abs=1e-4)
    lo, hi = wilson_interval(95, 100)
    assert lo == pytest.approx(0.8883, abs=1e-4) and hi == pytest.approx(0.9785, abs=1e-4)
    assert wilson_interval(10, 10)[1] == 1.0


def test_failure_drivers_name_the_parameter():
    rng = np.random.default_rng(0)
    r = rng.uniform(-10, 60, 40)
    other = rng.uniform(-5, 5, 40)
    failed = r > 30
    d = failure_drivers({"resistance": r, "bus_voltage": other}, failed, np.where(failed, 1.5, 0.5))
    assert d[0]["parameter"] == "resistance" and d[0]["rho_fail"] > 0.8 and d[0]["p_fail"] < 1e-6
    assert math.isnan(failure_drivers({"x": np.ones(5)}, np.zeros(5, bool), np.ones(5))[0]["rho_fail"])
