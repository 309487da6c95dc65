"""Where picdrive finds its templates, examples and build folders.

picdrive runs from a checkout installed with ``pip install -e .``: the Jinja2
templates (``firmware_templates/``), the bundled examples (``examples/``) and
the build folder (``firmware_build/``) live at the repository root, as the
design brief lays out.
"""
from __future__ import annotations

from pathlib import Path

_ROOT = Path(__file__).resolve().parents[2]


def repo_root() -> Path:
    """The repository root (the folder holding ``firmware_templates/``)."""
    if not (_ROOT / "firmware_templates").is_dir():
        raise RuntimeError(
            f"picdrive's firmware_templates/ folder is not at {_ROOT}: install picdrive from its "
            "checkout with 'pip install -e .' so that templates and examples are found")
    return _ROOT


def templates_dir() -> Path:
    return repo_root() / "firmware_templates"


def firmware_build_dir() -> Path:
    return repo_root() / "firmware_build"


def hil_dir() -> Path:
    return repo_root() / "hil"
