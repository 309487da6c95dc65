"""Firmware and twins for the identification tests and bench.

The board runs the firmware built from the profile the user has (whose motor values may be
wrong); the twin's plant is the true motor, wired as the test says.  The firmware's law is a
plain PI (identification does not use it).
"""
from __future__ import annotations

import hashlib
import math
from pathlib import Path

from picdrive.control_law import Rule, ScheduledLaw
from picdrive.result import DesignResult, save_design

PERMUTATIONS = ((0, 1, 2), (0, 2, 1), (1, 0, 2), (1, 2, 0), (2, 0, 1), (2, 1, 0))


def firmware_for(profile, root: Path, *, hex_build: bool = False, identify: bool = True) -> Path:
    """The identification firmware (``picdrive firmware --identify``) of ``profile`` (a PI law),
    generated once under ``root``; ``identify=False``: the drive firmware, without the mode."""
    from picdrive.firmware import codegen
    tag = hashlib.sha256(profile.sha256.encode()).hexdigest()[:10]
    out = Path(root) / f"{profile.name}.{tag}" if not identify else Path(root) / f"{profile.name}.{tag}.ident"
    if (out / "board.json").exists() and (not hex_build or (out / f"{profile.name}.hex").exists()):
        return out
    out.parent.mkdir(parents=True, exist_ok=True)
    rules = int(profile.design["rules"])
    vmax = 0.9 * profile.inverter.bus_voltage_v
    wmax = profile.control.speed_max_rpm * math.pi / 30.0
    law = ScheduledLaw(rules=tuple(Rule(0.01, 0.1, 0.0, 0.0) for _ in range(rules)),
                       premise_rad_s=(0.0, wmax) if rules > 1 else (0.0, 0.0),
                       sample_time_s=1.0 / profile.control.speed_loop_hz, u_min_v=-vmax, u_max_v=vmax)
    d = DesignResult(method="zn", status="verified", profile_name=profile.name, profile_sha256=profile.sha256,
                     law=law, variant="six-step")
    dpath = save_design(d, Path(root) / f"{profile.name}.{tag}.design.json")
    fw = codegen.generate(profile, dpath, identify=identify)
    return codegen.write_firmware(fw, out, check=False, hex_build=hex_build)


def twin_for(true_profile, firmware_dir: Path, *, hall_perm=(0, 1, 2), phase_perm=(0, 1, 2), seed: int = 0,
             hex_file: Path | None = None, **kw):
    """The twin of the true motor running ``firmware_dir``'s firmware, with the hall sensors
    wired to the board's hall inputs in the order ``hall_perm`` (input k reads sensor
    hall_perm[k]) and the motor's phases to the bridge's legs in the order ``phase_perm``."""
    from dataclasses import replace

    from picdrive_hil.twin import Twin, board_from_json, firmware_group
    board = board_from_json(Path(firmware_dir) / "board.json")
    pins = board.hall_pins
    # the sensor k's signal reaches the board pin of input j where hall_perm[j] == k
    hall_pins = tuple(pins[hall_perm.index(k)] for k in range(3))
    phase_pairs = tuple(board.phase_pairs[phase_perm.index(k)] for k in range(3))
    board = replace(board, hall_pins=hall_pins, phase_pairs=phase_pairs)
    if hex_file is not None:
        return Twin(true_profile, None, hex_file=hex_file, board=board, seed=seed, **kw)
    return Twin(true_profile, firmware=firmware_group(firmware_dir), board=board, seed=seed, **kw)
