"""The verification model against the motor twin: does the design's verification predict the drive?

For every committed design (examples/*.design.json) the firmware is generated
and run in the twin (firmware C + PIC peripheral model + three-phase plant,
in-process, free-running) through the verification's step and load step, and
the verification's six-step model (picdrive.models.simulate.simulate_six_step via
picdrive.analysis.steptest.run_sim) runs the same; both are judged by the same figures
(picdrive.analysis.steptest.step_figures: sector-mean speed) and must agree within the
tolerances below, and the twin must pass the limits the verification passed.

Tolerances (stated; from the agreement measured on the six committed designs,
docs/design-fuzzy.md "Validation against the twin", with room for the
rotor's start angle):

* rise time (10-90 %): within 25 % of the twin's (the model rises 5-20 %
  faster on duy2008: it carries the line current over each commutation,
  the twin's incoming phase has to build up against the EMF);
* overshoot: within 1.0 percentage point (the model under-predicts by up to
  0.7 point; the mixed-pid design keeps a 0.5 % bound in its GA for that);
* final speed under the load: within 0.1 % of the target;
* load dip: within 25 % of the twin's plus 1 rpm.
"""
import math
import warnings
from pathlib import Path

import pytest

from picdrive.paths import repo_root
from picdrive.profile import ProfileWarning, load_profile
from picdrive.result import load_design
from picdrive.analysis.steptest import VerifyConfig, run_sim, sim_plan, step_figures
from picdrive.gate import speed_measurement, three_phase_plant, twin_run

CASES = [(p, m) for p in ("duy2008", "assawinchaichote2016") for m in ("fuzzy-hinf", "mixed-pid", "zn")]

RISE_REL = 0.25
OVERSHOOT_PP = 1.0
FINAL_REL = 0.001
DIP_REL, DIP_ABS_RPM = 0.25, 1.0


def _profile(name):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ProfileWarning)
        return load_profile(name)


@pytest.mark.parametrize("profile_name, method", CASES, ids=[f"{p}-{m}" for p, m in CASES])
def test_verification_model_predicts_the_twin(profile_name, method, tmp_path):
    prof = _profile(profile_name)
    path = Path(repo_root()) / "examples" / f"{profile_name}.{method}.design.json"
    design = load_design(path, require_usable=True, profile=prof)
    plan = sim_plan(prof)
    twin = step_figures(twin_run(prof, path, plan, workdir=tmp_path), plan, prof)
    model = step_figures(run_sim(prof, design.law, plan, measurement=speed_measurement(prof, design.law), disturbances=False,
                                 three_phase=three_phase_plant), plan, prof)
    tgt = plan["target_rpm"]
    why = "twin " + ", ".join(f"{k} {twin[k]:.4g}" for k in ("rise_s", "overshoot_pct", "final_error_rpm",
                                                             "load_dip_rpm")) + \
          " | model " + ", ".join(f"{k} {model[k]:.4g}" for k in ("rise_s", "overshoot_pct", "final_error_rpm",
                                                                   "load_dip_rpm"))
    print(f"{profile_name} {method}: {why}")
    assert abs(model["rise_s"] - twin["rise_s"]) <= RISE_REL * twin["rise_s"], why
    assert abs(model["overshoot_pct"] - twin["overshoot_pct"]) <= OVERSHOOT_PP, why
    assert abs(model["final_error_rpm"] - twin["final_error_rpm"]) <= FINAL_REL * tgt, why
    assert abs(model["load_dip_rpm"] - twin["load_dip_rpm"]) <= DIP_REL * twin["load_dip_rpm"] + DIP_ABS_RPM, why
    # and the twin meets what the verification required of the model
    band = VerifyConfig.band
    assert twin["settling_s"] < 0.8 * plan["t_load_s"], why
    assert twin["overshoot_pct"] <= 100 * band, why
    assert twin["load_recovery_s"] < 0.8 * (plan["t_end_s"] - plan["t_load_s"]), why
    assert abs(twin["final_error_rpm"]) <= band * tgt, why
    assert twin["peak_current_a"] < prof.inverter.overcurrent_trip_a, why
    assert math.isfinite(twin["t_reach_s"])
