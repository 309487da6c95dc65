"""Compile the twin's C (plant, peripheral model, event loop) with a firmware
into a shared library, cached by content hash.

The cache key covers every source byte, every header the firmware folder
holds, the compiler flags and the compiler's version, so a change to any of
them rebuilds and nothing else does.  Builds go to a temporary name and are
renamed into place (whole or not at all), so parallel test workers can share
the cache.

Cache folder: ``$PICDRIVE_CACHE`` or ``$XDG_CACHE_HOME/picdrive`` or
``~/.cache/picdrive``, sub-folder ``twin/``.
"""
from __future__ import annotations

import functools
import hashlib
import os
import shutil
import subprocess
import tempfile
from pathlib import Path
from typing import Iterable, Sequence

from picdrive.errors import PicdriveError

CSRC = Path(__file__).resolve().parent / "csrc"

PLANT_SOURCES = ("plant.c",)
TWIN_SOURCES = ("plant.c", "pic.c", "twin.c")

CFLAGS = ("-std=c99", "-O2", "-fPIC", "-shared", "-Wall", "-Wextra",
          "-fno-strict-aliasing", "-D_DEFAULT_SOURCE")


class TwinBuildError(PicdriveError):
    """The twin's shared library could not be built (compiler missing or the C did not compile)."""


def cache_dir() -> Path:
    base = os.environ.get("PICDRIVE_CACHE")
    if base:
        root = Path(base)
    else:
        root = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "picdrive"
    d = root / "twin"
    d.mkdir(parents=True, exist_ok=True)
    return d


@functools.lru_cache(maxsize=None)
def _compiler_id(cc: str) -> str:
    try:
        out = subprocess.run([cc, "--version"], capture_output=True, text=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError) as e:
        raise TwinBuildError(f"C compiler {cc!r} not usable ({e}); install gcc (apt-get install gcc) "
                             "or set CC to a working compiler") from None
    return out.splitlines()[0] if out else cc


def _hash_inputs(files: Iterable[Path], extra: Sequence[str]) -> str:
    h = hashlib.sha256()
    for f in sorted(set(Path(p).resolve() for p in files)):
        h.update(str(f.name).encode() + b"\0")
        h.update(f.read_bytes())
        h.update(b"\0")
    for x in extra:
        h.update(x.encode() + b"\0")
    return h.hexdigest()[:24]


def build_library(sources: Sequence[Path], *, include_dirs: Sequence[Path] = (),
                  extra_inputs: Sequence[Path] = (), defines: Sequence[str] = (),
                  name: str = "libtwin", cflags: Sequence[str] = CFLAGS) -> Path:
    """Compile ``sources`` into one shared library (cached); returns its path."""
    cc = os.environ.get("CC", "gcc")
    headers: list[Path] = []
    for d in include_dirs:
        headers.extend(sorted(Path(d).glob("*.h")))
    inputs = list(sources) + headers + list(extra_inputs)
    for f in inputs:
        if not Path(f).is_file():
            raise TwinBuildError(f"twin build input {f} does not exist")
    argv_tail = list(cflags) + [f"-D{d}" for d in defines] + [f"-I{d}" for d in include_dirs]
    key = _hash_inputs(inputs, [_compiler_id(cc), *argv_tail, *[str(Path(s).name) for s in sources]])
    out = cache_dir() / f"{name}-{key}.so"
    if out.exists():
        return out
    fd, tmp = tempfile.mkstemp(prefix=f".{name}-", suffix=".so", dir=out.parent)
    os.close(fd)
    cmd = [cc, *argv_tail, "-o", tmp, *map(str, sources), "-lm"]
    res = subprocess.run(cmd, capture_output=True, text=True)
    if res.returncode != 0:
        os.unlink(tmp)
        raise TwinBuildError("building the twin failed:\n  " + " ".join(cmd) + "\n" + res.stderr.strip())
    os.replace(tmp, out)
    return out


def plant_library() -> Path:
    """The plant alone (no firmware, no peripheral model): for the cross-checks."""
    return build_library([CSRC / s for s in PLANT_SOURCES], include_dirs=[CSRC], name="libplant")


def private_copy(lib: Path) -> Path:
    """A private copy of a built library: each copy loaded with ctypes has its
    own globals (firmware state, SFRs), so several twins can live in one process."""
    d = Path(tempfile.mkdtemp(prefix="picdrive-twin-"))
    dst = d / lib.name
    shutil.copyfile(lib, dst)
    return dst
