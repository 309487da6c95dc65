"""verify_design rejects bad designs with a reason (the paper's printed K, an unstable law)."""
import warnings

import numpy as np
import pytest

from picdrive.control_law import Rule, ScheduledLaw
from picdrive.profile import load_profile
from picdrive.repro2016 import PRINTED
from picdrive.result import DesignResult
from picdrive.verify import VerifyConfig, sampled_closed_loop, verify_design


@pytest.fixture(scope="module")
def prof():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return load_profile("assawinchaichote2016")


def _result(prof, law=None, cert=None):
    return DesignResult(method="fuzzy-hinf", status="verified", profile_name=prof.name, profile_sha256=prof.sha256,
                        law=law, certificate=cert or {})


def test_paper_printed_K_rejected(prof):
    r = _result(prof, cert={"model": "paper-as-printed", "K": [PRINTED["K1"], PRINTED["K2"]]})
    verify_design(prof, r)
    assert r.status == "failed"
    assert r.verification["continuous_max_real_eig"]["ok"] is False
    assert r.verification["continuous_max_real_eig"]["value"] > 0
    assert any("continuous_max_real_eig" in why for why in r.reasons)


def test_unstable_law_rejected_without_simulating(prof):
    law = ScheduledLaw(rules=(Rule(kp=-5.0, ki=-50.0),), premise_rad_s=(0.0, 300.0), sample_time_s=1e-3,
                       u_min_v=-44.0, u_max_v=44.0)
    r = _result(prof, law=law)
    verify_design(prof, r)
    assert r.status == "failed"
    assert r.verification["sampled_spectral_radius"]["value"] > 1
    assert "sim_skipped" in r.verification
    assert any("sampled_spectral_radius" in why for why in r.reasons)


def test_law_beyond_the_bridge_rejected(prof):
    law = ScheduledLaw(rules=(Rule(kp=0.0, ki=1.0),), premise_rad_s=(0.0, 300.0), sample_time_s=1e-3,
                       u_min_v=-100.0, u_max_v=100.0)
    r = _result(prof, law=law)
    verify_design(prof, r, simulate=False)
    assert r.status == "failed" and r.verification["law_output_limits_v"]["ok"] is False


def test_sampled_closed_loop_matches_direct_iteration(prof):
    # the closed-loop matrix is the law + ZOH plant iterated by hand
    A = np.array([[-2.0, 1.0], [-1.0, -3.0]]); b = np.array([0.0, 1.5])
    g = Rule(kp=0.3, ki=2.0, kd=0.01, kc=0.2)
    ts = 0.01
    M = sampled_closed_loop(A, b, np.array([1.0, 0.0]), np.array([0.0, 1.0]), g, ts, 50.0)
    import scipy.linalg as sla
    E = sla.expm(np.block([[A, b[:, None]], [np.zeros((1, 3))]]) * ts)
    x = np.array([1.0, -0.5]); I = 0.2; yp = 0.7; d = 0.05
    a = ts / (ts + 1 / (2 * np.pi * 50.0))
    s = np.array([*x, I, yp, d])
    y, i = x[0], x[1]
    I2 = I + g.ki * ts * (-y)
    d2 = d + a * (g.kd * (yp - y) / ts - d)
    u = -g.kp * y + I2 + d2 - g.kc * i
    x2 = E[:2, :2] @ x + E[:2, 2] * u
    assert M @ s == pytest.approx(np.array([*x2, I2, y, d2]))


def test_good_pi_law_passes(prof):
    # an integral-dominated law on the six-step drive (b = 0; kp w* fits the 2 V headroom): every check passes
    law = ScheduledLaw(rules=(Rule(kp=0.02, ki=30.0),), premise_rad_s=(0.0, 314.0), sample_time_s=1e-3,
                       u_min_v=-44.16, u_max_v=44.16, setpoint_weight=0.0)
    r = _result(prof, law=law)
    verify_design(prof, r)
    bad = {k: v for k, v in r.verification.items() if not v["ok"]}
    assert r.ok, bad


def test_same_law_fails_when_too_aggressive(prof):
    # pure integral with ki = 100 V/rad draws 11.5 A on the step: above current_limit_a = 10 A
    law = ScheduledLaw(rules=(Rule(kp=0.0, ki=100.0),), premise_rad_s=(0.0, 314.0), sample_time_s=1e-3,
                       u_min_v=-44.16, u_max_v=44.16, setpoint_weight=0.0)
    r = _result(prof, law=law)
    verify_design(prof, r)
    assert r.status == "failed"
    assert r.verification["sim_peak_bus_current_a"]["value"] > prof.inverter.current_limit_a
