"""Where the console may write: picdrive's one output rule (:mod:`picdrive.outputs`, docs/outputs.md).

``step --png``, ``plot --png``, ``record``, ``scope --png/--csv`` and
``params save`` all pass their path through :func:`output_path` first:

* the path is made absolute (messages print absolute paths);
* missing folders are created, as by every other picdrive command; a parent
  that is a file, or a folder that cannot be written, is refused;
* an existing file is replaced only if picdrive wrote it (:func:`written_by_picdrive`:
  a CSV whose first line names picdrive, a PNG whose ``Software`` text chunk is
  picdrive's, a JSON whose ``format`` is picdrive's); anything else is refused.

What is written is written whole or not at all (temporary file + rename, in
:mod:`picdrive.console.record` and the plot savers).
"""
from __future__ import annotations

import json
import os
from pathlib import Path

from ..outputs import OutputError, file_output

__all__ = ["FileRuleError", "output_path", "written_by_picdrive", "write_png", "PNG_SOFTWARE"]

PNG_SOFTWARE = "picdrive"
"""Value of the PNG ``Software`` text chunk in every PNG the console writes."""


class FileRuleError(OutputError):
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
    try:
        p = file_output(p, p, what=what, same_kind=written_by_picdrive)
        p.parent.mkdir(parents=True, exist_ok=True)
    except OutputError as e:
        raise FileRuleError(str(e)) from None
    except OSError as e:
        raise FileRuleError(f"{what} {p}: cannot create folder {p.parent} ({e.strerror}); choose another path") from None
    return p


def write_png(fig, p: Path, dpi: int) -> None:
    """Save a matplotlib figure to ``p`` whole or not at all, with picdrive's ``Software`` mark.

    Temporary file beside ``p``, then rename; on an OSError the temporary
    file is removed and the error re-raised for the caller to word."""
    tmp = p.with_name(f".{p.name}.tmp.png")
    try:
        fig.savefig(tmp, dpi=dpi, metadata={"Software": PNG_SOFTWARE})
        os.replace(tmp, p)
    except OSError:
        tmp.unlink(missing_ok=True)
        raise
