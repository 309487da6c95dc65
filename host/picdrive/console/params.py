"""The board's parameters as the console explains, checks and keeps them.

* :data:`PARAM_HELP` -- what each parameter does, in the engineer's words
  (``help <param>``; the board's table gives unit, limits and default);
* :func:`cross_check` -- relations between parameters the board does not check
  one write at a time (a current limit of 0, a premise window upside down...);
* :func:`params_document` / :func:`read_params_file` -- a host backup of the
  board's persisted parameters (``params save/load/diff FILE``): JSON with the
  firmware identity, so a file is never pushed into a board of another build
  or motor without ``--force``.
"""
from __future__ import annotations

import datetime as _dt
import json
import re
from pathlib import Path

from ..errors import PicdriveError

__all__ = ["ParamsFileError", "PARAM_HELP", "param_help", "cross_check", "params_document",
           "read_params_file", "identity_differences", "FORMAT_ID", "ROUNDING_WARN"]

FORMAT_ID = "picdrive.params/1"
ROUNDING_WARN = 1e-3
"""A value the board stores more than 0.1 % away from the one asked is reported (``set``, ``load``)."""


class ParamsFileError(PicdriveError):
    """A parameter file that cannot be read or does not fit the board."""


PARAM_HELP = {
    "speed_setpoint": "Commanded mechanical speed; the sign is the direction. The ramp (accel_limit) "
                      "turns it into the 'setpoint' signal the loop follows.",
    "controller": "pid: rule 1's gains alone. fuzzy: the gains of all rules blended by the premise "
                  "memberships (|speed| between premise_low and premise_high).",
    "premise_low": "N1 of the fuzzy premise: at |speed| <= premise_low rule 1 acts alone; between N1 and N2 "
                   "the rules blend linearly. Must be below premise_high.",
    "premise_high": "N2 of the fuzzy premise: at |speed| >= premise_high the last rule acts alone. Must be "
                    "above premise_low.",
    "setpoint_weight": "b of the 2-DOF PID: the proportional term acts on b*r - y (1 = plain PID; lower "
                       "b softens the kick of a setpoint step without changing load rejection).",
    "u_min": "Lower limit of the law's output voltage (the integrator stops winding beyond it). Must be "
             "below u_max.",
    "u_max": "Upper limit of the law's output voltage (the integrator stops winding beyond it). Must be "
             "above u_min.",
    "current_limit": "Current the firmware holds the bus current to (back-EMF voltage window). 0 would allow "
                     "no torque: the next start latches STALL, so the console refuses it.",
    "accel_limit": "Setpoint ramp, rpm per second. 0 = no ramp: a setpoint change is a step.",
    "link_timeout": "Watchdog while running: with no valid frame from the host for this long the board "
                    "stops the motor and latches LINK_LOST. The console's heartbeat keeps it fed.",
    "stall_timeout": "Commanded to run with no hall edge for this long = STALL fault (outputs off).",
}
_RULE_HELP = {
    "kp": "Proportional gain of rule {j}, on b*r - y (volts per rad/s of speed error).",
    "ki": "Integral gain of rule {j} (volts per rad of accumulated speed error).",
    "kd": "Derivative gain of rule {j}, on the measured speed (not the setpoint: no derivative kick).",
    "kc": "Current-feedback gain of rule {j}: subtracts kc x the measured current from the output, damping "
          "the electrical mode (volts per ampere). 0 = no current feedback.",
}


def param_help(name: str, doc: str = "") -> str:
    """The explanation of parameter or signal ``name`` (the table's short doc if none here)."""
    if name in PARAM_HELP:
        return PARAM_HELP[name]
    m = re.fullmatch(r"rule(\d+)_(kp|ki|kd|kc)", name)
    if m:
        return _RULE_HELP[m.group(2)].format(j=m.group(1))
    return doc or "no description"


def cross_check(values: dict, involving: str | None = None) -> list[str]:
    """Problems of a parameter set (engineering units; names absent are not checked); with
    ``involving``, only the relations that parameter is part of."""
    out = []
    cl = values.get("current_limit")
    if cl is not None and cl <= 0:
        out.append(("current_limit", "current_limit 0 A allows no torque: the next start latches STALL; give "
                    "the motor's current limit (e.g. its rated current)"))
    lo, hi = values.get("premise_low"), values.get("premise_high")
    if lo is not None and hi is not None and not lo < hi:
        out.append(("premise_low premise_high", f"premise_low {lo:g} rpm must be below premise_high {hi:g} rpm "
                    "(the fuzzy blend runs from low to high)"))
    umin, umax = values.get("u_min"), values.get("u_max")
    if umin is not None and umax is not None and not umin < umax:
        out.append(("u_min u_max", f"u_min {umin:g} V must be below u_max {umax:g} V"))
    return [msg for names, msg in out if involving is None or involving in names.split()]


def _now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


def params_document(info, profile_name: str, entries, values: dict, raws: dict) -> dict:
    """The JSON document of ``params save``: identity and the persisted parameters."""
    return {
        "format": FORMAT_ID,
        "saved": _now(),
        "identity": {"build_id": f"0x{info.build_id:08x}", "table_hash": f"0x{info.table_hash:08x}",
                     "profile_hash": f"0x{info.profile_hash:08x}", "profile": profile_name,
                     "protocol": f"{info.proto_version[0]}.{info.proto_version[1]}"},
        "params": {e.name: {"value": values[e.name], "raw": int(raws[e.name]), "unit": e.unit} for e in entries},
    }


def read_params_file(path: str | Path) -> dict:
    """Read and check the shape of a ``params save`` file."""
    from ..fileio import read_input_text
    p = Path(path)
    text = read_input_text(p, "parameter file", limit_bytes=1 << 20, error=ParamsFileError)
    try:
        d = json.loads(text)
    except ValueError as e:
        raise ParamsFileError(f"{p} is not a JSON file ({e}); give a file written by 'params save'") from None
    if not isinstance(d, dict) or d.get("format") != FORMAT_ID:
        raise ParamsFileError(f"{p} is not a picdrive parameter file (format {FORMAT_ID}); write one with "
                              "'params save FILE'")
    ps, ident = d.get("params"), d.get("identity")
    if not isinstance(ps, dict) or not isinstance(ident, dict):
        raise ParamsFileError(f"{p}: 'params' and 'identity' must be objects")
    for k, v in ps.items():
        if not isinstance(v, dict) or not isinstance(v.get("raw"), int) or isinstance(v.get("raw"), bool):
            raise ParamsFileError(f"{p}: parameter {k!r} needs an integer 'raw' value")
    return d


def identity_differences(ident: dict, info) -> list[str]:
    """How a file's identity differs from the board's handshake."""
    board = {"build_id": f"0x{info.build_id:08x}", "table_hash": f"0x{info.table_hash:08x}",
             "profile_hash": f"0x{info.profile_hash:08x}"}
    return [f"{k} file {ident.get(k)} board {v}" for k, v in board.items() if ident.get(k) != v]
