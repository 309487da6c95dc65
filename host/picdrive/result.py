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
      "timings_s": {...}                wall times of the design steps
    }

A failed design may be written (for inspection) but :func:`load_design` with
``require_usable=True`` refuses it, and so does the firmware generator.
Files are written atomically: whole or not at all.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .errors import PicdriveError

import numpy as np

from . import __version__
from .control_law import ScheduledLaw, law_from_dict
from .fileio import atomic_write_text

SCHEMA_ID = "picdrive.design/1"
METHODS = ("fuzzy-hinf", "mixed-pid", "zn")

__all__ = ["DesignResult", "DesignError", "save_design", "load_design",
           "default_design_path", "atomic_write_text", "to_jsonable", "METHODS"]


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

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "DesignResult":
        if d.get("schema") != SCHEMA_ID:
            raise DesignError(f"not a picdrive design file (schema {d.get('schema')!r}, expected {SCHEMA_ID!r})")
        if d.get("method") not in METHODS:
            raise DesignError(f"unknown design method {d.get('method')!r}; expected one of {METHODS}")
        if d.get("status") not in ("verified", "failed"):
            raise DesignError(f"design status {d.get('status')!r} is neither 'verified' nor 'failed'")
        prof = d.get("profile") or {}
        try:
            law = None if d.get("law") is None else law_from_dict(d["law"])
        except (KeyError, TypeError, ValueError) as e:
            raise DesignError(f"design file has a malformed 'law': {e}") from None
        return cls(
            method=d["method"], variant=d.get("variant", ""), status=d["status"],
            reasons=list(d.get("reasons", [])), profile_name=prof.get("name", ""),
            profile_sha256=prof.get("sha256", ""), profile_path=prof.get("path"), law=law,
            options=d.get("options", {}), certificate=d.get("certificate", {}),
            verification=d.get("verification", {}), timings_s=d.get("timings_s", {}),
            picdrive_version=d.get("picdrive_version", ""))


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
    """Write a design result atomically (sorted keys, stable formatting)."""
    return atomic_write_text(path, json.dumps(result.to_dict(), indent=1, sort_keys=True) + "\n")


def load_design(path: str | Path, *, require_usable: bool = False, profile=None) -> DesignResult:
    """Read a design file.

    With ``require_usable`` a failed design, one without a firmware law, or
    one made from a different profile (``profile`` given, hash compared) is
    refused with a :class:`DesignError` that says why and what to do.
    """
    p = Path(path)
    try:
        d = json.loads(p.read_text(encoding="utf-8"))
    except OSError as e:
        raise DesignError(f"cannot read design file {p}: {e.strerror}") from None
    except json.JSONDecodeError as e:
        raise DesignError(f"design file {p} is not valid JSON: {e}") from None
    try:
        r = DesignResult.from_dict(d)
    except DesignError as e:
        raise DesignError(f"{p}: {e}") from None
    if require_usable:
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
    return r
