"""The ``picdrive`` command line.

Each subcommand lives in the module that owns the work; this file only
collects them.  A command module exposes ``register(subparsers)``, which adds
its parser and sets ``func`` (called with the parsed arguments, returning an
exit status).  Heavy imports (cvxpy, matplotlib) stay inside the command
functions so that ``picdrive --help`` is fast.
"""
from __future__ import annotations

import argparse
import importlib
import sys
import warnings

from . import __version__
from .errors import PicdriveError

# (module, purpose) in the order they appear in --help
COMMAND_MODULES = [
    "picdrive.gate",               # picdrive design
    "picdrive.papers.report",      # picdrive report
    "picdrive.firmware.codegen",   # picdrive firmware
    "picdrive_hil.cli",            # picdrive twin
    "picdrive.console.session",    # picdrive console
    "picdrive.console.identify",   # picdrive identify
    "picdrive.robustness.study",   # picdrive robustness
    "picdrive.demo",               # picdrive demo
]


class Parser(argparse.ArgumentParser):
    """argparse with picdrive's error format: one line on stderr (no usage block), exit status 2."""

    def error(self, message: str):
        sys.stderr.write(f"picdrive: error: {message}; see '{self.prog} --help'\n")
        raise SystemExit(2)


def build_parser() -> argparse.ArgumentParser:
    ap = Parser(
        prog="picdrive",
        description="BLDC speed drives on the PIC18F4431: design, firmware, serial link, motor twin.")
    ap.add_argument("--version", action="version", version=f"picdrive {__version__}")
    sub = ap.add_subparsers(dest="command", metavar="COMMAND")
    for modname in COMMAND_MODULES:
        importlib.import_module(modname).register(sub)
    return ap


def main(argv: list[str] | None = None) -> int:
    ap = build_parser()
    args = ap.parse_args(argv)
    if not getattr(args, "func", None):
        ap.print_help()
        return 2
    # profile warnings are part of the output, shown once, without source lines
    warnings.showwarning = lambda msg, cat, *a, **k: print(f"picdrive: warning: {msg}", file=sys.stderr)
    try:
        return int(args.func(args) or 0)
    except PicdriveError as e:
        print(f"picdrive: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("picdrive: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    raise SystemExit(main())
