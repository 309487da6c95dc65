"""Files and folders that appear whole or not at all.

Everything picdrive writes for the user (design results, generated firmware,
reports, recordings) goes through here: written under a temporary name in the
destination folder, then renamed into place, so an interrupted or failed run
leaves either the old output or the new one, never half of it.
"""
from __future__ import annotations

import os
import shutil
import stat
import tempfile
from pathlib import Path

from .errors import PicdriveError

__all__ = ["current_umask", "atomic_write_text", "new_temp_dir", "publish_dir", "read_input_text"]

_KINDS = ((stat.S_ISDIR, "a folder"), (stat.S_ISFIFO, "a FIFO (named pipe)"), (stat.S_ISCHR, "a character device"),
          (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket"))


def read_input_text(path: str | Path, what: str, *, limit_bytes: int, error=PicdriveError) -> str:
    """The text of an input file the user names (a profile, a design, a script), read with a type
    check and a size bound: a FIFO, a device (``/dev/zero``) or a folder is refused before it is
    opened (no hang, no unbounded read), so is a file over ``limit_bytes`` or not UTF-8 text.
    ``what`` names the input in the message ("profile", "session file"); ``error``: the
    :class:`PicdriveError` subclass raised."""
    p = Path(path)
    try:
        st = os.stat(p)
    except OSError as e:
        raise error(f"cannot read {what} {p}: {e.strerror}") from None
    if not stat.S_ISREG(st.st_mode):
        kind = next((k for test, k in _KINDS if test(st.st_mode)), "not a regular file")
        raise error(f"{what} {p} is {kind}, not a file: give the path of a {what} (a regular text file)")
    try:
        with open(p, "rb") as f:
            data = f.read(limit_bytes + 1)
    except OSError as e:
        raise error(f"cannot read {what} {p}: {e.strerror}") from None
    if len(data) > limit_bytes:
        raise error(f"{what} {p} is larger than {limit_bytes // 1024} KiB, far more than a {what} holds: "
                    f"check that this is the right file")
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as e:
        line = data[:e.start].count(b"\n") + 1
        raise error(f"{what} {p}: line {line}: byte 0x{data[e.start]:02X} is not UTF-8: a {what} is a UTF-8 "
                    "text file (this looks like a binary file, or text saved in another encoding: save it "
                    "as UTF-8)") from None


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
