"""The design-result file: what a design hands to the firmware generator.

One JSON file per design, by default next to its profile as
``<profile-stem>.<method>.design.json``.  Layout (schema
``picdrive.design/1``)::

    {
      "schema": "picdrive.design/1",
      "method": "fuzzy-hinf" | "mixed-pid" | "zn",
      "variant": "...",                 method-specific (e.g. "six-step", "paper")
      "status": "verified" | "failed",
      "reasons": ["..."],               why it failed (empty when verified)
      "profile": {"name": ..., "sha256": ..., "path": ...},
      "picdrive_version": "0.1.0",
      "options": {...},                 design options used
      "law": {...} | null,              picdrive.control_law.ScheduledLaw.to_dict(),
                                        null when the design cannot run on a
                                        six-step drive (e.g. the 2016 paper's
                                        two-input dq state feedback)
      "certificate": {...},             method-specific proof data (gamma, P, Y_j,
                                        K_j, H-inf norms...) as JSON numbers/lists
      "verification": {...},            figures measured after the design
      "timings_s": {...},               wall times of the design steps
      "signature": "sha256:..."         SHA-256 over the verified content (see below)
    }

The signature is a SHA-256 over what the verification vouches for: method,
variant, status, reasons, the profile's hash, the law, the certificate and the
verification figures (:func:`content_signature`).  picdrive writes it with the
file; :func:`load_design` with ``require_usable=True`` (what ``picdrive
firmware`` does) refuses a file whose content no longer matches it -- a gain
edited by hand with the status left "verified" -- and says to re-run
``picdrive design``.  It is a checksum against edits, not a secret: whoever
recomputes it can forge it.

A failed design may be written (for inspection) but :func:`load_design` with
``require_usable=True`` refuses it, and so does the firmware generator.
Files are written atomically: whole or not at all.
"""
from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .errors import PicdriveError
from .fileio import read_input_text

import numpy as np

from . import __version__
from .control_law import ScheduledLaw, law_from_dict
from .fileio import atomic_write_text
from .outputs import write_text

SCHEMA_ID = "picdrive.design/1"
METHODS = ("fuzzy-hinf", "mixed-pid", "zn")

__all__ = ["DesignResult", "DesignError", "save_design", "load_design", "content_signature",
           "default_design_path", "atomic_write_text", "to_jsonable", "METHODS"]

#: the parts of a design file the signature covers
SIGNED = ("schema", "method", "variant", "status", "reasons", "profile_sha256", "law", "certificate",
          "verification")


class DesignError(PicdriveError, ValueError):
    """A design file is unreadable, of the wrong schema, or not usable."""


@dataclass
class DesignResult:
    method: str
    status: str                          # "verified" | "failed"
    profile_name: str
    profile_sha256: str
    law: ScheduledLaw | None
    variant: str = ""
    reasons: list[str] = field(default_factory=list)
    profile_path: str | None = None
    options: dict[str, Any] = field(default_factory=dict)
    certificate: dict[str, Any] = field(default_factory=dict)
    verification: dict[str, Any] = field(default_factory=dict)
    timings_s: dict[str, float] = field(default_factory=dict)
    picdrive_version: str = __version__

    @property
    def ok(self) -> bool:
        return self.status == "verified" and not self.reasons

    def fail(self, reason: str) -> None:
        """Mark the design failed with a reason (keeps earlier reasons)."""
        self.status = "failed"
        self.reasons.append(reason)

    def to_dict(self) -> dict[str, Any]:
        return {
            "schema": SCHEMA_ID,
            "method": self.method,
            "variant": self.variant,
            "status": self.status,
            "reasons": list(self.reasons),
            "profile": {"name": self.profile_name, "sha256": self.profile_sha256, "path": self.profile_path},
            "picdrive_version": self.picdrive_version,
            "options": to_jsonable(self.options),
            "law": None if self.law is None else self.law.to_dict(),
            "certificate": to_jsonable(self.certificate),
            "verification": to_jsonable(self.verification),
            "timings_s": to_jsonable(self.timings_s),
        }

    def to_file_dict(self) -> dict[str, Any]:
        """:meth:`to_dict` with its :func:`content_signature` (what :func:`save_design` writes)."""
        d = self.to_dict()
        d["signature"] = content_signature(d)
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "DesignResult":
        if not isinstance(d, dict):
            raise DesignError(f"not a picdrive design file: the top level is a JSON {type(d).__name__}, expected "
                              "an object; re-run 'picdrive design' to write one")
        if d.get("schema") != SCHEMA_ID:
            raise DesignError(f"not a picdrive design file (schema {d.get('schema')!r}, expected {SCHEMA_ID!r})")
        if d.get("method") not in METHODS:
            raise DesignError(f"unknown design method {d.get('method')!r}; expected one of {METHODS}")
        if d.get("status") not in ("verified", "failed"):
            raise DesignError(f"design status {d.get('status')!r} is neither 'verified' nor 'failed'")
        for key, kind in (("variant", str), ("reasons", list), ("profile", dict), ("options", dict),
                          ("certificate", dict), ("verification", dict), ("timings_s", dict)):
            if key in d and d[key] is not None and not isinstance(d[key], kind):
                raise DesignError(f"design field {key!r} = {_short(d[key])}: expected a JSON "
                                  f"{ {str: 'string', list: 'list', dict: 'object'}[kind]}; re-run 'picdrive design'")
        prof = d.get("profile") or {}
        try:
            law = None if d.get("law") is None else _law(d["law"])
        except (KeyError, TypeError, ValueError) as e:
            raise DesignError(f"design file has a malformed 'law': {e}; re-run 'picdrive design'") from None
        return cls(
            method=d["method"], variant=d.get("variant") or "", status=d["status"],
            reasons=[str(x) for x in d.get("reasons") or []], profile_name=str(prof.get("name", "")),
            profile_sha256=str(prof.get("sha256", "")), profile_path=prof.get("path"), law=law,
            options=d.get("options") or {}, certificate=d.get("certificate") or {},
            verification=d.get("verification") or {}, timings_s=d.get("timings_s") or {},
            picdrive_version=str(d.get("picdrive_version", "")))


def _short(v: Any) -> str:
    t = json.dumps(v)
    return t if len(t) <= 40 else t[:37] + "..."


def _law(d: Any) -> ScheduledLaw:
    """:func:`~picdrive.control_law.law_from_dict` after checking every number is a finite JSON number."""
    if not isinstance(d, dict):
        raise ValueError(f"expected an object, found {_short(d)}")
    rules = d.get("rules")
    if not isinstance(rules, list) or not rules or not all(isinstance(r, dict) for r in rules):
        raise ValueError(f"'rules' = {_short(rules)}: expected a list of objects with kp, ki, kd, kc")

    def num(where: str, v: Any, optional: bool = False) -> None:
        if optional and v is None:
            return
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise ValueError(f"{where} = {_short(v)} is not a finite number")
    for j, r in enumerate(rules, 1):
        unknown = set(r) - {"kp", "ki", "kd", "kc"}
        if unknown:
            raise ValueError(f"rule {j} has unknown field(s) {sorted(unknown)}")
        for k in ("kp", "ki"):
            num(f"rule {j} {k}", r.get(k))
        for k in ("kd", "kc"):
            num(f"rule {j} {k}", r.get(k, 0.0))
    pr = d.get("premise_rad_s")
    if not isinstance(pr, list) or len(pr) != 2:
        raise ValueError(f"premise_rad_s = {_short(pr)}: expected [low, high]")
    num("premise_rad_s[0]", pr[0]), num("premise_rad_s[1]", pr[1])
    for k in ("sample_time_s", "u_min_v", "u_max_v"):
        num(k, d.get(k))
    for k in ("setpoint_weight", "kb_v_s_per_rad", "r_ohm"):
        num(k, d.get(k, 0.0))
    for k in ("derivative_filter_hz", "integrator_limit_v", "current_limit_a"):
        num(k, d.get(k), optional=True)
    if not isinstance(d.get("notes", ""), str):
        raise ValueError(f"notes = {_short(d.get('notes'))}: expected a string")
    return law_from_dict(d)


def content_signature(d: dict[str, Any]) -> str:
    """``"sha256:<hex>"`` over the signed parts (:data:`SIGNED`) of a design file's dict."""
    part = {k: d.get(k) for k in SIGNED if k != "profile_sha256"}
    prof = d.get("profile")
    part["profile_sha256"] = prof.get("sha256") if isinstance(prof, dict) else None
    text = json.dumps(part, sort_keys=True, separators=(",", ":"), ensure_ascii=True)
    return "sha256:" + hashlib.sha256(text.encode()).hexdigest()


def to_jsonable(x: Any) -> Any:
    """numpy arrays/scalars and complex numbers -> JSON-friendly values.

    Complex numbers become ``[re, im]``; non-finite floats become strings
    ("inf", "-inf", "nan") so the file stays strict JSON.
    """
    if isinstance(x, dict):
        return {str(k): to_jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [to_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return to_jsonable(x.tolist())
    if isinstance(x, (np.bool_, bool)):
        return bool(x)
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, (complex, np.complexfloating)):
        return [to_jsonable(float(x.real)), to_jsonable(float(x.imag))]
    if isinstance(x, (float, np.floating)):
        f = float(x)
        return f if math.isfinite(f) else ("nan" if math.isnan(f) else ("inf" if f > 0 else "-inf"))
    return x


def default_design_path(profile_path: str | Path, method: str) -> Path:
    p = Path(profile_path)
    return p.with_name(f"{p.stem}.{method}.design.json")


def save_design(result: DesignResult, path: str | Path) -> Path:
    """Write a design result atomically (sorted keys, stable formatting), with its signature."""
    return write_text(Path(path), json.dumps(result.to_file_dict(), indent=1, sort_keys=True) + "\n",
                      what="design file")


#: a design file is tens of kB (the certificate's matrices); far more is the wrong file
DESIGN_MAX_BYTES = 16 << 20


def load_design(path: str | Path, *, require_usable: bool = False, profile=None) -> DesignResult:
    """Read a design file.

    With ``require_usable`` a failed design, one without a firmware law, or
    one made from a different profile (``profile`` given, hash compared) is
    refused with a :class:`DesignError` that says why and what to do.
    """
    p = Path(path)
    text = read_input_text(p, "design file", limit_bytes=DESIGN_MAX_BYTES, error=DesignError)
    try:
        d = json.loads(text)
    except json.JSONDecodeError as e:
        raise DesignError(f"design file {p} is not valid JSON: {e}; give the .design.json 'picdrive design' "
                          "wrote") from None
    except RecursionError:
        raise DesignError(f"design file {p} is nested too deeply to be a design file") from None
    try:
        r = DesignResult.from_dict(d)
    except DesignError as e:
        raise DesignError(f"{p}: {e}") from None
    if require_usable:
        sig = d.get("signature")
        if sig is None:
            raise DesignError(f"design {p} has no signature (written by hand or by an older picdrive), so its "
                              "verification cannot be trusted; re-run 'picdrive design' to write a signed one")
        if sig != content_signature(d):
            raise DesignError(f"design {p} was changed after picdrive verified it (its content no longer matches "
                              "its signature); re-run 'picdrive design' instead of editing the file")
        if not r.ok:
            why = "; ".join(r.reasons) or "status is not 'verified'"
            raise DesignError(f"design {p} failed its verification ({why}); "
                              "re-run 'picdrive design' with other options and use a verified design")
        if r.law is None:
            raise DesignError(f"design {p} ({r.method}, variant {r.variant!r}) has no law the six-step firmware "
                              "can run; design with the six-step variant")
        if profile is not None and profile.sha256 and r.profile_sha256 != profile.sha256:
            raise DesignError(f"design {p} was made from profile {r.profile_name!r} with hash "
                              f"{r.profile_sha256[:12]}, but the profile given has hash {profile.sha256[:12]}; "
                              "re-run 'picdrive design' on this profile")
        if profile is not None:
            from .control_law import implausible_gains
            bad = implausible_gains(r.law, profile)
            if bad:
                raise DesignError(f"design {p}: {'; '.join(bad)}; a signed design with such a gain was edited "
                                  "and re-signed, not designed: re-run 'picdrive design' on this profile")
    return r
