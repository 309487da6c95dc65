"""Files and folders that appear whole or not at all.

Everything picdrive writes for the user (design results, generated firmware,
reports, recordings) goes through here: written under a temporary name in the
destination folder, then renamed into place, so an interrupted or failed run
leaves either the old output or the new one, never half of it.
"""
from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

__all__ = ["current_umask", "atomic_write_text", "new_temp_dir", "publish_dir"]


def current_umask() -> int:
    """The process umask (read without changing it for more than an instant)."""
    mask = os.umask(0)
    os.umask(mask)
    return mask


def atomic_write_text(path: str | Path, text: str) -> Path:
    """Write a text file whole or not at all (temp file + rename in the same folder)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8", newline="\n") as f:
            f.write(text)
        os.chmod(tmp, 0o666 & ~current_umask())   # mkstemp makes 0600; a written file gets the usual mode
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise
    return path


def new_temp_dir(out: str | Path) -> Path:
    """A fresh temporary folder beside ``out``, to be filled and then :func:`publish_dir`-ed."""
    out = Path(out)
    parent = out.parent if str(out.parent) else Path(".")
    parent.mkdir(parents=True, exist_ok=True)
    return Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".tmp", dir=parent))


def publish_dir(tmp: str | Path, out: str | Path) -> Path:
    """Move the filled temporary folder ``tmp`` to ``out``, replacing what was there.

    The old ``out`` is kept aside until the new one is in place and restored if
    the move fails.  The folder gets the umask's ordinary mode (mkdtemp makes
    0700)."""
    tmp, out = Path(tmp), Path(out)
    os.chmod(tmp, 0o777 & ~current_umask())
    old = None
    try:
        if out.exists():
            old = out.parent / f".{out.name}.old-{os.getpid()}"
            os.replace(out, old)
        os.replace(tmp, out)
    except BaseException:
        if old is not None and old.exists() and not out.exists():
            os.replace(old, out)
        raise
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)
    return out
