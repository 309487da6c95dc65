"""Compile the twin's C (plant, peripheral model, event loop) with a firmware
into a shared library, cached by content hash.

The firmware is compiled with its own flags and include folders (the ones
``picdrive.firmware.codegen.host_build`` gives, shim first) and the twin's C with the
twin's; the objects are linked into one library.  The cache key covers every
source and header byte, the flags and the compiler's version, so a change
to any of them rebuilds and nothing else does.  Builds go to a temporary
name and are renamed into place (whole or not at all), so parallel test
workers can share the cache.

Cache folder: ``$PICDRIVE_CACHE`` or ``$XDG_CACHE_HOME/picdrive`` or
``~/.cache/picdrive``, sub-folder ``twin/``.
"""
from __future__ import annotations

import functools
import hashlib
import os
import platform
import shutil
import subprocess
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

from picdrive.errors import PicdriveError
from picdrive.firmware.target import ENLARGED_FLASH_BYTES

CSRC = Path(__file__).resolve().parent / "csrc"

PLANT_SOURCES = ("plant.c",)
TWIN_SOURCES = ("plant.c", "pic.c", "twin.c")
# the twin's C is compiled as one unit (twin_all.c includes the three), so that the
# inner loop's calls between plant, peripheral model and event loop inline
TWIN_UNITY = "twin_all.c"
# the library's writable data, for the restore between twins (picdrive_hil.twin): its own unit
REGION = "region.c"

# -ffp-contract=off: no fused multiply-adds, whatever the target, so the arithmetic
# (and every result) is the same as written; -fvisibility=hidden: only the C API
# (twin.h, default visibility) is exported, internal calls bind directly.
TWIN_CFLAGS = ("-std=c99", "-O3", "-g", "-fno-math-errno", "-ffp-contract=off", "-fvisibility=hidden",
               "-Wall", "-Wextra", "-fno-strict-aliasing", "-D_DEFAULT_SOURCE")
COMMON = ("-fPIC",)

# x86-64 micro-architecture levels (the psABI's), by the /proc/cpuinfo flags each needs
_X86_LEVELS = (
    ("x86-64-v3", {"avx", "avx2", "bmi1", "bmi2", "f16c", "fma", "abm", "movbe", "xsave"}),
    ("x86-64-v2", {"cx16", "lahf_lm", "popcnt", "pni", "sse4_1", "sse4_2", "ssse3"}),
)


class TwinError(PicdriveError):
    """The twin could not be built or started, or the firmware did something
    the twin reports as an error (interrupt storm, wrong baud rate...)."""


class TwinBuildError(PicdriveError):
    """The twin's shared library could not be built (compiler missing or the C did not compile)."""


@dataclass(frozen=True)
class Group:
    """C sources compiled with the same include folders and flags."""

    sources: tuple[Path, ...]
    include_dirs: tuple[Path, ...] = ()
    cflags: tuple[str, ...] = TWIN_CFLAGS
    extra_inputs: tuple[Path, ...] = field(default=())


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


def _cpu_flags() -> set[str]:
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("flags"):
                    return set(line.split(":", 1)[1].split())
    except OSError:
        pass
    return set()


@functools.lru_cache(maxsize=None)
def target_flags() -> tuple[str, ...]:
    """``-march=x86-64-v3`` (or ``-v2``) when this machine's CPU has that level and the
    compiler knows it, else nothing.  The library is built (and cached) on the machine
    that runs it, and the level is part of the cache key.  The arithmetic does not
    change with the level (no fused multiply-add: ``-ffp-contract=off``); the code is
    shorter (VEX three-operand forms, ``roundsd`` for floor).  ``$PICDRIVE_TWIN_MARCH``
    overrides: a level name, or ``none``."""
    want = os.environ.get("PICDRIVE_TWIN_MARCH")
    if want is not None:
        return () if want.strip().lower() in ("", "none") else (f"-march={want.strip()}",)
    if platform.machine().lower() not in ("x86_64", "amd64"):
        return ()
    have = _cpu_flags()
    cc = os.environ.get("CC", "gcc")
    for level, need in _X86_LEVELS:
        if need <= have:
            try:
                ok = subprocess.run([cc, f"-march={level}", "-x", "c", "-c", "-o", os.devnull, "-"],
                                    input="int x;\n", capture_output=True, text=True).returncode == 0
            except OSError:
                ok = False
            if ok:
                return (f"-march={level}",)
    return ()


def core_cflags() -> tuple[str, ...]:
    """The PIC18 core's extra flags (with GCC): its run loop (pic18cpu.c) ends every handler with
    its own indirect jump (threaded dispatch); GCC would merge those identical tails into one
    shared jump (cross-jumping, and computed-goto blocks longer than 8 insns are not copied back),
    which the branch predictor then sees as one jump with ~60 targets.  Pure code layout: the
    arithmetic is the same.  Clang keeps the jumps apart by itself."""
    if "clang" in _compiler_id(os.environ.get("CC", "gcc")).lower():
        return ()
    return ("-fno-crossjumping", "--param=max-goto-duplication-insns=40")


def twin_cflags() -> tuple[str, ...]:
    """The flags of the twin's own C: ``TWIN_CFLAGS`` + ``target_flags()``."""
    return TWIN_CFLAGS + target_flags()


def _group_inputs(g: Group) -> list[Path]:
    files = list(g.sources) + list(g.extra_inputs)
    for d in g.include_dirs:
        files.extend(sorted(Path(d).glob("*.h")))
    return files


def _inputs_signature(groups: Sequence[Group]) -> tuple:
    """What the inputs of a build are on disk now, cheaply: each include folder's modification
    time and each input file's size, modification time and inode (a file written or replaced, or
    a header added to or removed from a folder, changes it)."""
    sig = []
    for g in groups:
        for d in g.include_dirs:
            sig.append((str(d), os.stat(d).st_mtime_ns))
        for f in _group_inputs(g):
            st = os.stat(f)
            sig.append((str(f), st.st_size, st.st_mtime_ns, st.st_ino))
    return tuple(sig)


# per process: (name, compiler, groups) -> (inputs' signature, built library): a library asked for
# again with unchanged inputs is not hashed again (a tolerance study starts thousands of twins)
_BUILT: dict[tuple, tuple[tuple, Path]] = {}


def build_library(groups: Sequence[Group], *, name: str = "libtwin") -> Path:
    """Compile each group with its flags and link all into one shared library
    (cached); returns its path."""
    cc = os.environ.get("CC", "gcc")
    key = (name, cc, tuple(groups))
    try:
        sig = _inputs_signature(groups)
    except OSError:
        sig = None                       # a missing input: the build below says which
    got = _BUILT.get(key)
    if sig is not None and got is not None and got[0] == sig and got[1].exists():
        return got[1]
    out = _build_library(groups, name, cc)
    if sig is not None:
        _BUILT[key] = (sig, out)
    return out


def _build_library(groups: Sequence[Group], name: str, cc: str) -> Path:
    h = hashlib.sha256(_compiler_id(cc).encode())
    for g in groups:
        for f in _group_inputs(g):
            if not Path(f).is_file():
                raise TwinBuildError(f"twin build input {f} does not exist")
            h.update(Path(f).name.encode() + b"\0" + Path(f).read_bytes() + b"\0")
        h.update(("|".join(g.cflags) + "|" + "|".join(Path(d).name for d in g.include_dirs)).encode())
    out = cache_dir() / f"{name}-{h.hexdigest()[:24]}.so"
    if out.exists():
        return out
    with tempfile.TemporaryDirectory(prefix="picdrive-build-") as tmpd:
        objs = []
        for gi, g in enumerate(groups):
            for si, src in enumerate(g.sources):
                obj = Path(tmpd) / f"g{gi}_{si}_{Path(src).stem}.o"
                cmd = [cc, *g.cflags, *COMMON, *[f"-I{d}" for d in g.include_dirs], "-c", str(src), "-o", str(obj)]
                res = subprocess.run(cmd, capture_output=True, text=True)
                if res.returncode != 0:
                    raise TwinBuildError("building the twin failed:\n  " + " ".join(cmd) + "\n" + res.stderr.strip())
                objs.append(str(obj))
        fd, tmp = tempfile.mkstemp(prefix=f".{name}-", suffix=".so", dir=out.parent)
        os.close(fd)
        cmd = [cc, "-shared", *COMMON, "-o", tmp, *objs, "-lm"]
        res = subprocess.run(cmd, capture_output=True, text=True)
        if res.returncode != 0:
            os.unlink(tmp)
            raise TwinBuildError("linking the twin failed (missing fw_init/fw_poll/fw_isr_high/fw_isr_low? "
                                 "architecture.md seam 4):\n  " + " ".join(cmd) + "\n" + res.stderr.strip())
        os.replace(tmp, out)
    return out


def twin_group(gen_dir: Path) -> Group:
    """The twin's own C: plant, peripheral model, event loop."""
    return Group((CSRC / TWIN_UNITY, CSRC / REGION), (CSRC, Path(gen_dir)), twin_cflags(),
                 tuple(CSRC / s for s in TWIN_SOURCES) + (CSRC / "twin.h", CSRC / "pic_internal.h"))


PIL_UNITY = "twin_pil_all.c"
# the processor twin's memories when the firmware does not fit the 18F4431: the enlarged
# linker script's (picdrive.firmware.target.enlarged_lkr: ENLARGED_FLASH_BYTES of flash, GPRs to
# 0x5FF).  Only on request.
ENLARGED_RAM_END = 0x600


def pil_group(gen_dir: Path, *, enlarged: bool = False) -> Group:
    """The processor twin's C: the PIC18 core, plant, peripheral model, event loop (no firmware
    C: the core runs the HEX).  ``enlarged``: 128 KB of flash and 1.5 KB of GPRs instead of
    the 18F4431's 16 KB and 768 B, for a HEX linked with the enlarged measurement script."""
    flags = twin_cflags() + core_cflags() + ("-DTWIN_PIL", "-DPIC18_TRACK_RAM")
    if enlarged:
        flags += (f"-DPIC18_FLASH_BYTES=0x{ENLARGED_FLASH_BYTES:X}u", f"-DPIC18_RAM_END=0x{ENLARGED_RAM_END:X}u")
    return Group((CSRC / PIL_UNITY, CSRC / REGION), (CSRC, Path(gen_dir)), flags,
                 tuple(CSRC / s for s in TWIN_SOURCES) +
                 tuple(CSRC / s for s in ("pil.c", "pic18cpu.c", "pic18cpu.h", "twin.h", "pic_internal.h")))


def plant_library() -> Path:
    """The plant alone (no firmware, no peripheral model): for the cross-checks."""
    return build_library([Group(tuple(CSRC / s for s in PLANT_SOURCES), (CSRC,), twin_cflags())],
                         name="libplant")


def private_copy(lib: Path) -> Path:
    """A private copy of a built library: each copy loaded with ctypes has its
    own globals (firmware state, SFRs), so several twins can live in one process."""
    d = Path(tempfile.mkdtemp(prefix="picdrive-twin-"))
    dst = d / lib.name
    shutil.copyfile(lib, dst)
    return dst
