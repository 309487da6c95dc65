"""argparse types shared by the commands: each refuses a bad value with a one-line reason.

argparse prints their message as ``picdrive: error: argument --gamma: ...``
(see :class:`picdrive.cli.Parser`).
"""
from __future__ import annotations

import argparse
import math


def _number(text: str, kind):
    try:
        v = kind(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not {'an integer' if kind is int else 'a number'}") from None
    if kind is float and not math.isfinite(v):
        raise argparse.ArgumentTypeError(f"{text!r} is not a finite number")
    return v


def finite_float(text: str) -> float:
    """Any finite number."""
    return _number(text, float)


def positive_float(text: str) -> float:
    """A finite number > 0."""
    v = _number(text, float)
    if not v > 0:
        raise argparse.ArgumentTypeError(f"{text!r}: expected a number > 0")
    return v


def nonneg_float(text: str) -> float:
    """A finite number >= 0."""
    v = _number(text, float)
    if not v >= 0:
        raise argparse.ArgumentTypeError(f"{text!r}: expected a number >= 0")
    return v


def seed(text: str) -> int:
    """A random seed: an integer in [0, 2^31 - 1] (numpy's generators take no negative seed)."""
    v = _number(text, int)
    if not 0 <= v <= 2**31 - 1:
        raise argparse.ArgumentTypeError(f"{text!r}: expected an integer in [0, 2147483647]")
    return v


def port(text: str) -> int:
    """A TCP port, 0 (any free port) to 65535."""
    v = _number(text, int)
    if not 0 <= v <= 65535:
        raise argparse.ArgumentTypeError(f"{text!r}: expected 0..65535 (0 = any free port)")
    return v
