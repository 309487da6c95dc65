"""``picdrive design``: run a design method on a profile, verify it, save it.

Each method module exposes ``design(profile, *, progress=True, **options)
-> DesignResult``; the result comes back already verified by
:mod:`picdrive.design.verify` (status ``verified`` or ``failed`` with reasons).
This module only dispatches, prints the summary and writes the file:

* a verified design goes to ``<profile-stem>.<method>.design.json`` next to
  the profile, or to ``-o``;
* a failed design is never written there: it goes to
  ``<...>.design.failed.json`` for inspection, an existing good design is left
  untouched, and the command exits 1.
"""
from __future__ import annotations

import importlib
import json
import math
import os
from pathlib import Path
from typing import Any

from ..errors import PicdriveError
from ..result import METHODS, SCHEMA_ID, DesignResult, default_design_path, save_design

# method name -> module implementing design(profile, **options)
METHOD_MODULES = {
    "fuzzy-hinf": "picdrive.design.fuzzy_hinf",
    "mixed-pid": "picdrive.design.mixed_pid",
    "zn": "picdrive.design.zn",
}
assert set(METHOD_MODULES) == set(METHODS)


def run_design(profile, method: str, *, progress: bool = True, **options: Any) -> DesignResult:
    """Design and verify; returns the result (does not write anything)."""
    if method not in METHOD_MODULES:
        raise PicdriveError(f"unknown design method {method!r}; choose one of {', '.join(METHOD_MODULES)}")
    from ..firmware.fixedpoint import check_profile_arithmetic
    check_profile_arithmetic(profile)      # a profile the firmware cannot hold: refused before the work
    mod = importlib.import_module(METHOD_MODULES[method])
    return mod.design(profile, progress=progress, **options)


def _is_design_file(path: Path) -> bool:
    """A design file picdrive wrote (a design may replace it; anything else is the user's)."""
    try:
        d = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return False
    return isinstance(d, dict) and d.get("schema") == SCHEMA_ID


def output_path(profile, method: str, out: str | None, ok: bool) -> Path:
    """Where the design goes (checked by :func:`picdrive.outputs.file_output`): ``-o`` (a file, or a
    folder: an existing one or a path ending in '/'), else next to the profile."""
    from ..outputs import file_output
    if profile.path is not None:
        default = default_design_path(profile.path, method)
    else:
        default = Path(f"{profile.name}.{method}.design.json")
    if not ok:
        default = default.with_name(default.name.replace(".design.json", "") + ".design.failed.json")
    if out and not ok and not (out.endswith(("/", os.sep)) or Path(out).is_dir()):
        p = Path(out)
        out = str(p.with_name(p.name.replace(".design.json", "") + ".design.failed.json"))
    return file_output(out, default, what="design file", same_kind=_is_design_file)


def _parse_option(text: str) -> tuple[str, Any]:
    if "=" not in text:
        raise PicdriveError(f"--option {text!r}: expected KEY=VALUE (for example --option gamma=0.5)")
    k, v = text.split("=", 1)
    k = k.strip().replace("-", "_")
    if not k:
        raise PicdriveError(f"--option {text!r}: the KEY is empty; expected KEY=VALUE (for example --option rules=3)")
    try:
        val = json.loads(v)
    except json.JSONDecodeError:
        val = v
    if isinstance(val, float) and not math.isfinite(val):
        raise PicdriveError(f"--option {text!r}: {k} must be a finite number")
    return k, val


def summary_lines(r: DesignResult) -> list[str]:
    out = [f"method      {r.method}" + (f" ({r.variant})" if r.variant else ""),
           f"profile     {r.profile_name} ({r.profile_sha256[:12]})",
           f"status      {r.status.upper()}"]
    for reason in r.reasons:
        out.append(f"  reason    {reason}")
    if r.law is not None:
        out.append(f"law         {r.law.n_rules} rule(s), b = {r.law.setpoint_weight:g}, "
                   f"u in [{r.law.u_min_v:.3g}, {r.law.u_max_v:.3g}] V, Ts = {r.law.sample_time_s * 1e3:g} ms")
        for j, g in enumerate(r.law.rules, 1):
            out.append(f"  rule {j}    kp={g.kp:.6g} V/(rad/s)  ki={g.ki:.6g} V/rad  kd={g.kd:.6g} V s^2/rad  kc={g.kc:.6g} V/A")
    else:
        out.append("law         none: not realisable on a six-step drive")
    for k, v in r.verification.items():
        if isinstance(v, dict) and "value" in v:
            lim = f" (limit {v['limit']})" if "limit" in v else ""
            ok = "" if v.get("ok", True) else "  FAILED"
            out.append(f"  check     {k}: {v['value']}{lim}{ok}")
    for k, v in r.timings_s.items():
        out.append(f"  time      {k}: {v:.3f} s")
    return out


def _cmd(args) -> int:
    from ..profile import load_profile
    profile = load_profile(args.profile)
    opts = dict(_parse_option(o) for o in args.option)
    for name in ("variant", "gamma", "seed", "optimizer", "preset"):
        v = getattr(args, name)
        if v is not None:
            opts[name] = v
    # both destinations are checked before the work, so a refusal costs nothing
    output_path(profile, args.method, args.output, True)
    output_path(profile, args.method, args.output, False)
    r = run_design(profile, args.method, progress=not args.no_progress, **opts)
    for line in summary_lines(r):
        print(line)
    path = output_path(profile, args.method, args.output, r.ok)
    save_design(r, path)
    if r.ok:
        print(f"wrote {path}")
        return 0
    print(f"design FAILED its verification; wrote it for inspection only to {path}")
    return 1


def register(sub) -> None:
    from ..argtypes import positive_float, seed
    p = sub.add_parser("design", help="design a speed controller from a drive profile",
                       description="Design, verify and save a speed controller.")
    p.add_argument("--profile", required=True, help="profile .toml, or a bundled profile name (duy2008, assawinchaichote2016)")
    p.add_argument("--method", required=True, choices=list(METHOD_MODULES))
    p.add_argument("-o", "--output", help="output file, or folder (existing, or ending in '/': created) "
                   "(default: next to the profile); an existing file is replaced only if it is a design file")
    p.add_argument("--variant", help="method variant (fuzzy-hinf: six-step | tracking | paper)")
    p.add_argument("--gamma", type=positive_float, help="fuzzy-hinf: prescribed H-inf level (default: minimise)")
    p.add_argument("--seed", type=seed, help="mixed-pid: GA seed (default: profile design.ga_seed)")
    p.add_argument("--optimizer", help="mixed-pid: ga | de (scipy differential evolution)")
    p.add_argument("--preset", help="zn: paper2016 for the 2016 paper's Kp=0.43, Ki=2.30, Kd=0.28")
    p.add_argument("--option", action="append", default=[], metavar="KEY=VALUE",
                   help="any other method option (repeatable), e.g. --option rules=3")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=_cmd)
