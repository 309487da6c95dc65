"""HIL suite helpers: the board under test behind picdrive.link.

``--target twin`` (default): each test gets a motor twin running firmware
generated at test time with ``picdrive firmware`` (codegen) from a bundled
profile and its committed design, served in real time on a local socket;
the suite talks to it only through ``picdrive.link``, and additionally reads
the twin's true plant state and injects faults where a test needs that.

``--target <serial URL>``: a real board of profile ``--profile``; the suite
finds which bundled design its firmware runs by comparing the board's gains
with each design's law.  Tests that need a physical injection (hall fault,
overcurrent, load torque, plant perturbation) are skipped there.

Every limit comes from the profile or the design result (see ``Limits``).
"""
from __future__ import annotations

import math
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest

from picdrive.link import protocol as P
from picdrive.link.client import Link, LinkError
from picdrive.analysis.metrics import step_metrics
from picdrive.profile import ProfileWarning, load_profile
from picdrive.result import load_design

ROOT = Path(__file__).resolve().parents[2]
PROFILES = ("duy2008", "assawinchaichote2016", "duy2008_halls")
METHODS = ("fuzzy-hinf", "mixed-pid", "zn")

def profile(name):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ProfileWarning)
        return load_profile(name)


def design_path(profile_name: str, method: str) -> Path:
    return ROOT / "examples" / f"{profile_name}.{method}.design.json"


@dataclass
class Limits:
    """Pass limits of a step, from the profile and the design's own verification (the same
    criteria the verification applied to its six-step model, which tests/test_verify_twin.py
    checks predicts the twin)."""

    target_rpm: float
    settle_s: float          # design verification: settled within 80 % of its step phase (sim_settling_s)
    band_pct: float          # design verification: final-error band (% of its step target)
    overshoot_pct: float     # design verification: sim_overshoot_pct limit (the settling band: no braking),
                             # and never above control.speed_max_rpm
    load_recovery_s: float   # design verification: back in the band within 80 % of its load phase

    @classmethod
    def of(cls, prof, design, target_rpm: float | None = None) -> "Limits":
        v = design.verification
        tgt = prof.speed_step_rpm() if target_rpm is None else target_rpm
        band = 100.0 * v["sim_final_error_rpm"]["limit"] / v["sim_step_target_rpm"]["value"]
        overshoot = min(float(v["sim_overshoot_pct"]["limit"]),
                        100.0 * (prof.control.speed_max_rpm - abs(tgt)) / abs(tgt))
        return cls(tgt, _within(v["sim_settling_s"]), band, overshoot, _within(v["sim_load_recovery_s"]))


def _within(check: dict) -> float:
    """The time limit a verification check applied: its ``limit`` (a record with ``phase_s``), or 80 % of the
    phase an older record gave as its ``limit``."""
    return float(check["limit"]) if "phase_s" in check else 0.8 * float(check["limit"])


@dataclass
class Bench:
    link: Link
    profile: object
    design: object
    method: str
    label: str
    twin: object = None
    server: object = None
    report: list = field(default_factory=list)

    @property
    def is_twin(self) -> bool:
        return self.twin is not None

    def need_twin(self, what: str) -> None:
        if self.twin is None:
            pytest.skip(f"{what} needs a physical injection the link cannot do; runs against the twin")

    def limits(self, target_rpm: float | None = None) -> Limits:
        return Limits.of(self.profile, self.design, target_rpm)

    def close(self) -> None:
        try:
            if not self.link.closed:
                try:                        # leave a real board stopped, not to its watchdog
                    self.link.stop()
                except LinkError:           # best effort: the link is closed next either way
                    pass
            self.link.close()
        finally:
            if self.server is not None:
                self.server.stop()
            if self.twin is not None:
                self.twin.close()

    # -- measurements through the link ---------------------------------------
    def record(self, seconds: float, signals=("speed", "setpoint", "current", "state")) -> np.ndarray:
        """Telemetry at the speed-loop rate for ``seconds`` (after the call returns)."""
        self.link.configure_telemetry(signals, decimation=1)
        return self.link.read_samples(seconds=seconds)

    def stream(self, signals=("speed", "setpoint", "current", "state")) -> None:
        self.link.configure_telemetry(signals, decimation=1)

    def collect(self, seconds: float) -> np.ndarray:
        return self.link.read_samples(seconds=seconds)

    def wait_state(self, state: P.State, timeout: float = 2.0) -> None:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if self.link.status().state == state:
                return
            time.sleep(0.01)
        raise AssertionError(f"board did not reach state {state.name} in {timeout} s "
                             f"(status {self.link.status()})")

    def settle_at(self, rpm: float, seconds: float) -> None:
        """Run to rpm and wait (the motor is running after this)."""
        self.link.set_speed(rpm)
        if self.link.status().state != P.State.RUN:
            self.link.start()
        time.sleep(seconds)


def sector_speed(prof, data: np.ndarray, target: float, *, breaks=()) -> np.ndarray:
    """The measured speed averaged over one hall sector at the target speed (picdrive.analysis.steptest.sector_mean):
    the speed a six-step drive regulates; inside a sector the pair's EMF, hence the torque per ampere,
    ripples with the rotor angle (the 2016 motor under its 1 N m load: about +-2.5 % at 76 Hz with a
    PID, which no 1 kHz speed law removes).  The design's verification judges the same mean.
    ``breaks``: sample indices where a new phase of the run starts (the setpoint step): no window
    reaches across one."""
    from picdrive.analysis.steptest import sector_mean
    t = data["t"]
    ts = float(np.median(np.diff(t))) if t.size > 1 else 1.0 / prof.control.speed_loop_hz
    return sector_mean(prof, data["speed"].astype(float), ts, target, breaks=breaks)


def step_of(data: np.ndarray, target: float, prof=None):
    """Step metrics of telemetry data, measured from the sample where the setpoint reached target
    (on the sector-mean speed when the profile is given)."""
    sp = data["setpoint"]
    k = int(np.argmax(np.abs(sp - target) <= abs(target) * 1e-3 + 0.5))
    if abs(sp[k] - target) > abs(target) * 1e-3 + 0.5:
        raise AssertionError(f"the setpoint never reached {target} rpm in the record")
    t = data["t"]
    y = data["speed"] if prof is None else sector_speed(prof, data, target, breaks=(k,))
    return step_metrics(t, y, target, y0=float(data["speed"][k]), t_step=float(t[k])), k


class FirmwareCache:
    """Firmware of each (profile, method), generated once per session as ``picdrive firmware``
    generates it: the host compile check and the chip's HEX within every budget (a firmware over
    one fails the test that asks for it), the HEX for the processor twin."""

    def __init__(self, root: Path):
        self.root = root
        self.dirs: dict[tuple[str, str], Path] = {}

    def hex(self, profile_name: str, method: str) -> Path:
        """The HEX ``picdrive firmware`` built into the firmware folder (it fits the 18F4431)."""
        folder = self.get(profile_name, method)
        return folder / f"{profile(profile_name).name}.hex"

    def get(self, profile_name: str, method: str) -> Path:
        key = (profile_name, method)
        if key not in self.dirs:
            from picdrive.firmware import codegen
            prof = profile(profile_name)
            fw = codegen.generate(prof, str(design_path(profile_name, method)))
            self.dirs[key] = codegen.write_firmware(fw, self.root / f"{profile_name}.{method}", check=True,
                                                    hex_build=True)
        return self.dirs[key]


def match_design(link: Link, prof) -> tuple[str, object]:
    """The bundled design whose law the board runs (gains within their quantisation)."""
    best = None
    for method in METHODS:
        p = design_path(prof.name, method)
        if not p.exists():
            continue
        d = load_design(p, require_usable=False, profile=prof)
        if d.law is None:
            continue
        err = 0.0
        for j, rule in enumerate(d.law.rules, start=1):
            for g in ("kp", "ki", "kd", "kc"):
                name = f"rule{j}_{g}"
                if name not in link.table:          # the board has fewer rules than this design
                    err = math.inf
                    break
                e = link.param(name)
                board = link.get(name)
                err = max(err, abs(board - getattr(rule, g)) / max(abs(getattr(rule, g)), e.scale * 2))
        if best is None or err < best[0]:
            best = (err, method, d)
    if best is None or best[0] > 0.05:
        pytest.fail(f"the board's gains match none of the bundled {prof.name} designs: load one "
                    f"(picdrive console, 'load examples/{prof.name}.<method>.design.json') or flash its firmware")
    return best[1], best[2]


