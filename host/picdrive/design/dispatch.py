"""The design methods by name: each method module exposes ``design(profile, *, drive,
progress=True, **options) -> DesignResult``, and the result comes back verified by
:mod:`picdrive.design.verify` (status ``verified`` or ``failed`` with reasons).
``picdrive design`` itself (the built drive, the output rule, the summary) is
:mod:`picdrive.gate`.
"""
from __future__ import annotations

import importlib
from typing import Any

from ..errors import PicdriveError
from ..result import METHODS, DesignResult

# method name -> module implementing design(profile, *, drive, **options)
METHOD_MODULES = {
    "fuzzy-hinf": "picdrive.design.fuzzy_hinf",
    "mixed-pid": "picdrive.design.mixed_pid",
    "zn": "picdrive.design.zn",
}
assert set(METHOD_MODULES) == set(METHODS)


def design(profile, method: str, *, drive, progress: bool = True, **options: Any) -> DesignResult:
    """Run ``method`` on ``profile``; the result comes back verified against ``drive`` (or failed).

    Parameters
    ----------
    profile : picdrive.profile.Profile
        The drive (SI units inside; speeds at the interface in rpm).
    method : str
        ``"fuzzy-hinf"``, ``"mixed-pid"`` or ``"zn"`` (:data:`METHOD_MODULES`).
    drive : object
        The built drive the verification needs beyond the models
        (:func:`picdrive.design.verify.verify_design`; :class:`picdrive.gate.BuiltDrive`).
    progress : bool
        Print the method's progress lines.
    **options
        The method's own options (``picdrive design -O key=value``), recorded in the result.

    Returns
    -------
    picdrive.result.DesignResult
        The law (gains in V/(rad/s), V/rad, V s^2/rad, V/A; limits in V; sample time in s), the
        verification's figures with their units, and ``status`` ``"verified"`` or ``"failed"``.

    Raises
    ------
    PicdriveError
        An unknown method.
    """
    if method not in METHOD_MODULES:
        raise PicdriveError(f"unknown design method {method!r}; choose one of {', '.join(METHOD_MODULES)}")
    mod = importlib.import_module(METHOD_MODULES[method])
    return mod.design(profile, drive=drive, progress=progress, **options)
