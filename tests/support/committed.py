"""The committed example designs (examples/<profile>.<method>.design.json) against a design
computed now from the code with the same (default) options."""
from __future__ import annotations

import pytest

from picdrive.paths import repo_root
from picdrive.result import load_design


def assert_reproduces(profile, result, *, rel: float) -> None:
    """``result`` (a design just computed) equals the committed design of its profile and method:
    status, variant, options and every number of the law, within ``rel`` (the LMI solver's results
    vary in the last digits between machines; the GA and ZN are deterministic)."""
    path = repo_root() / "examples" / f"{profile.name}.{result.method}.design.json"
    committed = load_design(path, require_usable=True, profile=profile)     # missing or stale: fails
    assert (result.status, result.variant) == (committed.status, committed.variant)
    assert result.options == committed.options
    a, b = result.law, committed.law
    assert len(a.rules) == len(b.rules)
    for ra, rb in zip(a.rules, b.rules):
        for k in ("kp", "ki", "kd", "kc"):
            assert getattr(ra, k) == pytest.approx(getattr(rb, k), rel=rel, abs=1e-12), (path.name, k)
    for k in ("premise_rad_s", "sample_time_s", "u_min_v", "u_max_v", "setpoint_weight", "derivative_filter_hz",
              "i_lim_v", "current_limit_a", "kb_v_s_per_rad", "r_ohm"):
        assert getattr(a, k) == pytest.approx(getattr(b, k), rel=rel), (path.name, k)
