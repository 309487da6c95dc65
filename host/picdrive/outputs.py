"""Where picdrive may write: the one output rule every command follows.

Every command that writes for the user (``picdrive design``, ``firmware``,
``report``, ``demo``, ``twin --eeprom``) resolves its destination here before
it starts working, and writes through here, so that the rule is the same
everywhere (``docs/outputs.md``):

* **Never remove what picdrive did not write.**  An output *folder* is
  written only where nothing is, into an empty folder, or over a folder
  picdrive wrote itself: one holding picdrive's marker file
  (:data:`MARKER`, a manifest of the files picdrive put there with their
  SHA-256) in which every file is still the one picdrive wrote (or lies in a
  folder the manifest declares regenerable, like the firmware's ``build/``
  that ``make`` creates).  A folder holding anything else is refused with
  the names of what would be lost.
* An output *file* replaces only a file of the same kind picdrive writes
  (a design file is replaced only by a design file); a folder, a device or
  any other file is refused.
* Missing folders are **created** (with their parents), whether the path is
  a folder output or the folder part of a file output.  A path that ends in
  ``/`` names a folder; for a file output the file goes into it under its
  default name.
* The output folder cannot be the current folder or one that holds it
  (``-o .``): name a subfolder.
* A destination that cannot be written (``/proc``, permission denied, a
  parent that is a file) is refused before any work is done, with the
  reason.  Writes are atomic (temporary name in the destination folder, then
  rename): a failure leaves the old output or nothing, never half of one.

Errors are :class:`OutputError` (a :class:`~picdrive.errors.PicdriveError`):
one line naming the path, what is there and what to do.
"""
from __future__ import annotations

import hashlib
import errno
import json
import os
import shutil
import tempfile
from pathlib import Path
from typing import Callable, Iterable

from . import fileio
from .errors import PicdriveError

__all__ = ["MARKER", "OutputError", "file_output", "dir_output", "write_text", "write_bytes", "new_temp_dir",
           "publish_dir", "manifest_text"]

#: the marker file picdrive writes into every folder it writes whole
MARKER = ".picdrive-output"
MARKER_SCHEMA = "picdrive.output/1"


class OutputError(PicdriveError):
    """An output path picdrive must not or cannot write."""


# ---------------------------------------------------------------------------
# helpers
# ---------------------------------------------------------------------------
def _names_folder(text: str) -> bool:
    return text.endswith("/") or text.endswith(os.sep)


def _nearest_existing(path: Path) -> Path:
    p = path
    while not os.path.lexists(p):
        if p.parent == p:
            break
        p = p.parent
    return p


def _reason(e: OSError, folder: Path) -> str:
    """Why a file cannot be made in ``folder``, in words that fit: creating a file in /proc fails
    with ENOENT, "No such file or directory", although the folder is there."""
    if e.errno == errno.ENOENT and folder.is_dir():
        return "it takes no new files: a virtual file system such as /proc"
    return e.strerror or str(e)


def _check_writable_parent(path: Path, what: str) -> None:
    """The folder that will hold ``path`` exists or can be created, and a file can be made in it.

    Probes with a temporary file in the nearest existing ancestor (removed at once): root passes
    every permission bit, so only an attempt tells about /proc, read-only mounts and the like."""
    anc = _nearest_existing(path.parent)
    if not anc.is_dir():
        raise OutputError(f"{what} {path}: {anc} is a file, not a folder; choose an output path whose folders "
                          "are folders")
    try:
        fd, tmp = tempfile.mkstemp(prefix=".picdrive-probe.", dir=anc)
    except OSError as e:
        raise OutputError(f"{what} {path}: cannot write in {anc} ({_reason(e, anc)}); choose a folder you "
                          "can write to") from None
    os.close(fd)
    os.unlink(tmp)


def _inside_cwd(path: Path) -> bool:
    try:
        cwd = Path.cwd().resolve()
    except OSError:
        return False
    p = path.resolve()
    return p == cwd or p in cwd.parents


def _sha256_file(p: Path) -> str:
    h = hashlib.sha256()
    with open(p, "rb") as f:
        for block in iter(lambda: f.read(1 << 16), b""):
            h.update(block)
    return h.hexdigest()


def _walk_files(folder: Path) -> list[str]:
    """Relative paths (``/``-separated) of every file, link or other non-folder under ``folder``."""
    out = []
    for root, dirs, files in os.walk(folder):
        r = Path(root)
        for name in files + [d for d in dirs if (r / d).is_symlink()]:
            out.append((r / name).relative_to(folder).as_posix())
        dirs[:] = [d for d in dirs if not (r / d).is_symlink()]
    return sorted(out)


def manifest_text(command: str, files: dict[str, bytes | str], *, regenerable: Iterable[str] = ()) -> str:
    """The marker of a folder holding ``files`` (relative path -> content), written by ``command``.

    ``regenerable``: subfolders whose content others derive from picdrive's files (the
    firmware Makefile's ``build/``); picdrive may replace them with the folder."""
    digests = {}
    for rel, content in files.items():
        if rel == MARKER:
            continue
        data = content.encode("utf-8") if isinstance(content, str) else content
        digests[rel] = hashlib.sha256(data).hexdigest()
    return json.dumps({"schema": MARKER_SCHEMA, "written_by": f"picdrive {command}",
                       "note": "picdrive replaces this folder whole when asked to write here again, as long as "
                               "every file below is the one it wrote; keep your own files elsewhere",
                       "regenerable": sorted(regenerable), "files": dict(sorted(digests.items()))},
                      indent=1, sort_keys=True) + "\n"


def _foreign_files(folder: Path) -> list[str]:
    """Files in a picdrive output folder that picdrive did not write (or that were changed since)."""
    try:
        man = json.loads((folder / MARKER).read_text(encoding="utf-8"))
        files, regen = dict(man["files"]), [str(r).rstrip("/") for r in man.get("regenerable", [])]
        if man.get("schema") != MARKER_SCHEMA:
            raise ValueError
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return [f"{MARKER} (not a marker picdrive can read)"]
    foreign = []
    for rel in _walk_files(folder):
        if rel == MARKER or any(rel == r or rel.startswith(r + "/") for r in regen):
            continue
        p = folder / rel
        if rel not in files or p.is_symlink() or not p.is_file():
            foreign.append(rel)
        elif _sha256_file(p) != files[rel]:
            foreign.append(f"{rel} (changed since picdrive wrote it)")
    return foreign


# ---------------------------------------------------------------------------
# the rule
# ---------------------------------------------------------------------------
def file_output(arg: str | os.PathLike | None, default: Path, *, what: str = "output file",
                same_kind: Callable[[Path], bool] | None = None) -> Path:
    """Resolve and check the destination of an output file.

    ``arg``: the user's ``-o`` (None: ``default``).  A path ending in ``/`` or
    naming an existing folder gets the file under ``default.name``.
    ``same_kind(path)`` says whether an existing file is one picdrive may
    replace (None: any existing regular file is refused).
    Returns the file path; raises :class:`OutputError`."""
    if arg is None or str(arg) == "":
        path = Path(default)
    else:
        text = os.fspath(arg)
        path = Path(text)
        if _names_folder(text) or path.is_dir():
            path = path / Path(default).name
    if path.is_dir():
        raise OutputError(f"{what} {path} is a folder; name a file, or a folder with a trailing '/' to write "
                          f"{Path(default).name} into it")
    if os.path.lexists(path):
        if path.is_symlink() or not path.is_file():
            raise OutputError(f"{what} {path} exists and is not a regular file; choose another path")
        if same_kind is None or not same_kind(path):
            raise OutputError(f"{what} {path} exists and is not a file picdrive wrote; picdrive does not "
                              "replace it: choose another path or move that file away")
    _check_writable_parent(path, what)
    return path


def dir_output(arg: str | os.PathLike, *, what: str = "output folder") -> Path:
    """Check the destination of an output folder (see the module docstring); returns it."""
    out = Path(os.fspath(arg))
    if str(arg) == "" or _inside_cwd(out):
        raise OutputError(f"{what} {str(arg) or '(empty)'!s} is the current folder or holds it; picdrive writes "
                          "its folders whole, so name a new subfolder, e.g. -o out/")
    if os.path.lexists(out):
        if out.is_symlink():
            raise OutputError(f"{what} {out} is a symbolic link (to {os.readlink(out)}); picdrive replaces its "
                              "output folders whole, which would replace the link, not write into its folder: "
                              "give the folder itself or a new path")
        if not out.is_dir():
            raise OutputError(f"{what} {out} exists and is not a folder; choose another path or move it away")
        try:
            entries = os.listdir(out)
        except OSError as e:
            raise OutputError(f"{what} {out}: cannot read it ({e.strerror}); choose another folder") from None
        if entries:
            if MARKER not in entries:
                raise OutputError(f"{what} {out} is not empty and was not written by picdrive "
                                  f"(no {MARKER} marker); picdrive replaces only its own output folders: choose "
                                  "a new or empty folder")
            foreign = _foreign_files(out)
            if foreign:
                more = f" and {len(foreign) - 3} more" if len(foreign) > 3 else ""
                raise OutputError(f"{what} {out} holds files picdrive did not write ({', '.join(foreign[:3])}{more}); "
                                  "picdrive would replace the folder whole: move them away or choose another "
                                  "folder")
    _check_writable_parent(out, what)
    return out


def write_text(path: Path, text: str, *, what: str = "output file") -> Path:
    """Write a file checked by :func:`file_output`, atomically."""
    try:
        return fileio.atomic_write_text(path, text)
    except OSError as e:
        raise OutputError(f"cannot write {what} {path}: {_reason(e, path.parent)}; choose a folder you can "
                          "write to") from None


def write_bytes(path: Path, data: bytes, *, what: str = "output file") -> Path:
    """Write a binary file checked by :func:`file_output`, atomically (temp file + rename)."""
    tmp = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.chmod(tmp, 0o666 & ~fileio.current_umask())
        os.replace(tmp, path)
    except OSError as e:
        if tmp is not None and os.path.exists(tmp):
            os.unlink(tmp)
        raise OutputError(f"cannot write {what} {path}: {_reason(e, path.parent)}; choose a folder you can "
                          "write to") from None
    return path


def new_temp_dir(out: Path, *, what: str = "output folder") -> Path:
    """A temporary folder beside ``out`` (to be filled, then :func:`publish_dir`-ed)."""
    try:
        return fileio.new_temp_dir(out)
    except OSError as e:
        raise OutputError(f"cannot write {what} {out}: {e.strerror or e}; choose a folder you can write to") from None


def publish_dir(tmp: Path, out: Path, command: str, *, regenerable: Iterable[str] = (),
                what: str = "output folder") -> Path:
    """Put the filled temporary folder in place of ``out``, whole.

    Writes the marker (unless ``tmp`` already holds one), checks ``out`` again
    (it may have changed while picdrive worked) and renames.  On any error the
    temporary folder is removed and ``out`` is as it was."""
    try:
        if not (tmp / MARKER).exists():
            files = {rel: (tmp / rel).read_bytes() for rel in _walk_files(tmp)}
            (tmp / MARKER).write_text(manifest_text(command, files, regenerable=regenerable), encoding="utf-8")
        dir_output(out, what=what)
        fileio.publish_dir(tmp, out)
    except OSError as e:
        shutil.rmtree(tmp, ignore_errors=True)
        raise OutputError(f"cannot write {what} {out}: {e.strerror or e}; choose a folder you can write to") from None
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return out
