"""Where the console may write: one rule for every file it writes.

``step --png``, ``plot --png``, ``record``, ``scope --png/--csv`` and
``params save`` all pass their path through :func:`output_path` first:

* the path is made absolute (messages print absolute paths);
* a missing parent folder is refused with a message naming it -- the console
  never creates folders (a typo must not grow a directory tree);
* an existing file is replaced only if picdrive wrote it (:func:`written_by_picdrive`:
  a CSV whose first line names picdrive, a PNG whose ``Software`` text chunk is
  picdrive's, a JSON whose ``format`` is picdrive's); anything else is refused.

What is written is written whole or not at all (temporary file + rename, in
:mod:`picdrive.console_record` and the plot savers).
"""
from __future__ import annotations

import json
from pathlib import Path

from .errors import PicdriveError

__all__ = ["FileRuleError", "output_path", "written_by_picdrive", "PNG_SOFTWARE"]

PNG_SOFTWARE = "picdrive"
"""Value of the PNG ``Software`` text chunk in every PNG the console writes."""


class FileRuleError(PicdriveError):
    """An output path the console will not write."""


def written_by_picdrive(p: Path) -> bool:
    """True if the existing file ``p`` carries picdrive's mark (see the module doc)."""
    try:
        with open(p, "rb") as f:
            head = f.read(8192)
    except OSError:
        return False
    ext = p.suffix.lower()
    if ext == ".png":
        return head.startswith(b"\x89PNG") and b"tEXtSoftware\x00" + PNG_SOFTWARE.encode() in head
    if ext == ".csv":
        first = head.split(b"\n", 1)[0]
        return first.startswith(b"# picdrive")
    if ext == ".json":
        try:
            d = json.loads(p.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            return False
        return isinstance(d, dict) and str(d.get("format", "")).startswith("picdrive.")
    return False


def output_path(path: str | Path, ext: str, what: str) -> Path:
    """The absolute path the console may write ``what`` to, or :class:`FileRuleError`.

    ``ext``: the required suffix (``".png"``, ``".csv"``, ``".json"``).
    """
    p = Path(path).expanduser().absolute()
    if p.suffix.lower() != ext:
        raise FileRuleError(f"{what} {str(path)!r}: the file name must end in {ext}")
    if p.is_dir():
        raise FileRuleError(f"{what} {p}: is a folder; give a file name ending in {ext}")
    folder = p.parent
    if not folder.is_dir():
        what_is = "is a file, not a folder" if folder.exists() else "does not exist"
        raise FileRuleError(f"{what} {p}: folder {folder} {what_is}; create it first (the console does not "
                            "create folders) or choose another path")
    if p.exists() and not written_by_picdrive(p):
        raise FileRuleError(f"{what} {p}: a file picdrive did not write is there; choose another name "
                            "(picdrive never overwrites files it did not write)")
    return p
