"""Render the C link module for a table and compile it with the fake app.

Builds are cached by content hash under ``$TMPDIR/picdrive_linksupport/`` so a test
session (or a bench run) compiles each variant once.
"""
from __future__ import annotations

import hashlib
import re
import os
import shutil
import subprocess
import tempfile
from pathlib import Path

from picdrive.link import protocol as P
from picdrive.firmware.p18f4431 import bits
from picdrive.link.protocol_c import render_c

HERE = Path(__file__).resolve().parent
CACHE = Path(tempfile.gettempdir()) / f"picdrive_linksupport_{os.getuid()}"

STRICT = ["-std=c99", "-Wall", "-Wextra", "-Werror", "-Wconversion", "-pedantic"]
AVR = ["avr-gcc", "-mmcu=atmega328p", "-std=c99", "-Os", "-Wall", "-Wextra", "-Werror", "-Wconversion"]
SANITIZE = ["-fsanitize=address,undefined", "-fno-sanitize-recover=all", "-fno-omit-frame-pointer"]

DEFAULT_BUILD_ID = 0xB0A4D001
DEFAULT_PROFILE_HASH = 0x1234ABCD


def render(table: P.Table | None = None, *, build_id: int = DEFAULT_BUILD_ID,
           profile_hash: int = DEFAULT_PROFILE_HASH, sample_hz: float | None = 1000,
           capture_bytes: int = P.CAPTURE_BYTES_DEFAULT) -> dict[str, str]:
    table = table if table is not None else P.build_table(2)
    return render_c(table, build_id=build_id, profile_hash=profile_hash, sample_hz=sample_hz,
                      capture_bytes=capture_bytes, sfr_bits=bits())


def _run(cmd: list[str], cwd: Path) -> None:
    r = subprocess.run(cmd, cwd=cwd, capture_output=True, text=True)
    if r.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed:\n{r.stdout}{r.stderr}")


def _cached(key_parts: list[bytes], name: str, build) -> Path:
    key = hashlib.sha256(b"\0".join(key_parts)).hexdigest()[:20]
    out = CACHE / key / name
    if out.exists():
        return out
    CACHE.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix="build-", dir=CACHE))
    try:
        build(tmp)
        final = CACHE / key
        try:
            os.rename(tmp, final)
        except OSError:                      # another process won the race
            shutil.rmtree(tmp, ignore_errors=True)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    return out


def _write_sources(d: Path, files: dict[str, str]) -> None:
    for k, v in files.items():
        (d / k).write_text(v)
    for k in ("fake_app.c", "fake_hooks.h", "fuzz_main.c"):
        if (HERE / k).exists():
            shutil.copy(HERE / k, d / k)


def _support_bytes() -> list[bytes]:
    return [(HERE / k).read_bytes() for k in ("fake_app.c", "fake_hooks.h", "fuzz_main.c") if (HERE / k).exists()]


def shared_library(files: dict[str, str] | None = None, *, sanitize: bool = False) -> Path:
    """The rendered module (strict warnings) + fake_app.c as a shared library."""
    files = files if files is not None else render()
    flags = ["-O1", "-g", "-fPIC"] + (SANITIZE if sanitize else [])

    def build(d: Path) -> None:
        _write_sources(d, files)
        _run(["gcc", *STRICT, *flags, "-include", "fake_hooks.h", "-c", "link_fw.c", "-o", "link_fw.o"], d)
        _run(["gcc", "-std=c99", "-Wall", "-Wextra", "-Werror", *flags, "-c", "fake_app.c", "-o", "fake_app.o"], d)
        _run(["gcc", "-shared", *flags, "link_fw.o", "fake_app.o", "-o", "libfakeboard.so"], d)

    return _cached([files["link_fw.h"].encode(), files["link_fw.c"].encode(), *_support_bytes(),
                    " ".join(flags).encode(), b"so"], "libfakeboard.so", build)


def fuzz_executable(files: dict[str, str] | None = None) -> Path:
    """The fuzz harness (fuzz_main.c + fake_app.c + the module) under ASan and UBSan."""
    files = files if files is not None else render()
    flags = ["-O1", "-g"] + SANITIZE

    def build(d: Path) -> None:
        _write_sources(d, files)
        _run(["gcc", *STRICT, *flags, "-include", "fake_hooks.h", "-c", "link_fw.c", "-o", "link_fw.o"], d)
        _run(["gcc", "-std=c99", "-Wall", "-Wextra", "-Werror", *flags, "-c", "fake_app.c", "-o", "fake_app.o"], d)
        _run(["gcc", "-std=c99", "-Wall", "-Wextra", "-Werror", *flags, "-c", "fuzz_main.c", "-o", "fuzz_main.o"], d)
        _run(["gcc", *flags, "link_fw.o", "fake_app.o", "fuzz_main.o", "-o", "fuzz_link"], d)

    return _cached([files["link_fw.h"].encode(), files["link_fw.c"].encode(), *_support_bytes(),
                    " ".join(flags).encode(), b"fuzz"], "fuzz_link", build)


def avr_object(files: dict[str, str], d: Path) -> Path:
    """Compile link_fw.c with avr-gcc (16-bit int) into d; returns the object."""
    for k, v in files.items():
        (d / k).write_text(v)
    _run([*AVR, "-c", "link_fw.c", "-o", "link_fw_avr.o"], d)
    return d / "link_fw_avr.o"


def avr_ram_bytes(obj: Path) -> dict[str, int]:
    """RAM symbols (.bss/.data, incl. common) of an AVR object, from avr-nm --size-sort -S."""
    r = subprocess.run(["avr-nm", "--size-sort", "-S", str(obj)], capture_output=True, text=True, check=True)
    out = {}
    for line in r.stdout.splitlines():
        parts = line.split()
        if len(parts) == 4 and parts[2] in "bBdDC":
            out[parts[3]] = int(parts[1], 16)
    return out


SDCC_HOME = Path(os.environ.get("PICDRIVE_SDCC", Path.home() / ".cache/picdrive/toolchain/sdcc-4.2.0-pic16"))
from picdrive.firmware.target import SDCC_FLAGS   # the image's options (--obanksel=N miscompiles link_fw.c)


def sdcc_asm(files: dict[str, str], d: Path) -> str:
    """Compile link_fw.c for the PIC18F4431 with SDCC's pic16 port (scripts/pic_toolchain.sh installs
    it); returns the generated assembly."""
    from picdrive.firmware.p18f4431 import render_sdcc_device
    sdcc = SDCC_HOME / "bin" / "sdcc"
    if not sdcc.exists():
        raise RuntimeError(f"SDCC pic16 not found at {sdcc}: run scripts/pic_toolchain.sh")
    for k, v in files.items():
        (d / k).write_text(v)
    xc_h, _ = render_sdcc_device()
    (d / "xc.h").write_text(xc_h)
    env = {**os.environ, "PATH": f"{SDCC_HOME / 'bin'}:{os.environ.get('PATH', '')}"}
    r = subprocess.run([str(sdcc), *SDCC_FLAGS, "-I.", "-c", "link_fw.c"], cwd=d, capture_output=True, text=True,
                       env=env)
    if r.returncode != 0:
        raise RuntimeError(f"sdcc failed:\n{r.stdout[-3000:]}{r.stderr[-3000:]}")
    return (d / "link_fw.asm").read_text()


def asm_call_graph(asm: str) -> dict[str, set[str]]:
    """Function -> functions it calls (CALL/RCALL/GOTO to a symbol), from SDCC pic16 assembly."""
    graph: dict[str, set[str]] = {}
    cur = None
    for line in asm.splitlines():
        m = re.match(r"^(_\w+):", line)
        if m and not re.match(r"^_\d+_DS_", line):
            cur = m.group(1)
            graph.setdefault(cur, set())
            continue
        m = re.match(r"^\s+(?:CALL|RCALL|GOTO)\s+(_\w+)", line)
        if m and cur is not None and not re.match(r"_\d+_DS_", m.group(1)):
            graph[cur].add(m.group(1))
    return graph


def reachable(graph: dict[str, set[str]], roots) -> set[str]:
    seen, todo = set(), list(roots)
    while todo:
        f = todo.pop()
        if f in seen:
            continue
        seen.add(f)
        todo += graph.get(f, ())
    return seen
