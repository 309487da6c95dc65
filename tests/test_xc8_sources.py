"""main_xc8.c and config_xc8.c -- the two files only XC8 builds -- compiled against something.

config_xc8.c goes through SDCC's pic16 port with the 18F4431 device header rendered from
p18f4431.inc: its ``#pragma config`` lines reach gpasm as CONFIG directives, and gpasm checks every
setting and value against the chip's CONFIG table.  main_xc8.c goes through gcc against the
generated register shim (``host/xc.h``: the ``__interrupt`` qualifier compiles to nothing there), so
the vectors must call the firmware's entry points exactly as drive.h declares them.  Each check is
shown to fail on a broken file."""
import re
import subprocess
import warnings
from pathlib import Path

import pytest

from picdrive.firmware import codegen, p18f4431, target
from picdrive.paths import firmware_build_dir, repo_root
from picdrive.profile import load_profile

COMMITTED = firmware_build_dir() / "duy2008"


@pytest.fixture(scope="module")
def folders(tmp_path_factory):
    """The committed firmware and one generated now for the other bundled profile."""
    tmp = tmp_path_factory.mktemp("xc8")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")                # its speed range warning
        prof = load_profile("assawinchaichote2016")
    fw = codegen.generate(prof, str(repo_root() / "examples" / "assawinchaichote2016.mixed-pid.design.json"))
    return [COMMITTED, codegen.write_firmware(fw, tmp / "fw", check=False)]


@pytest.fixture(scope="module")
def device(tmp_path_factory):
    d = tmp_path_factory.mktemp("device")
    xc_h, xc_sfr = p18f4431.render_sdcc_device()
    (d / "xc.h").write_text(xc_h)
    (d / "xc_sfr.c").write_text(xc_sfr)
    return d


def _sdcc(device: Path, src: Path, work: Path) -> subprocess.CompletedProcess:
    tc = target.toolchain()
    work.mkdir(parents=True, exist_ok=True)
    return subprocess.run([str(tc.sdcc), "-mpic16", "-p18f4431", "--std-c99", "--no-warn-non-free",
                           f"-I{device}", "-c", str(src), "-o", str(work / (src.stem + ".o"))],
                          cwd=work, capture_output=True, text=True, timeout=120)


def _gcc(folder: Path, main: Path) -> subprocess.CompletedProcess:
    # XC8's main is void; its config pragmas mean nothing to gcc
    return subprocess.run(["gcc", "-std=c99", "-fsyntax-only", "-Wall", "-Wextra", "-Werror", "-Wno-main",
                           "-Wno-unknown-pragmas", f"-I{folder / 'host'}", f"-I{folder}", str(main)],
                          capture_output=True, text=True, timeout=60)


def test_config_bits_assemble_for_the_18f4431(folders, device, tmp_path):
    for k, folder in enumerate(folders):
        src = folder / "config_xc8.c"
        r = _sdcc(device, src, tmp_path / str(k))
        assert r.returncode == 0, r.stdout + r.stderr
        pragmas = re.findall(r"^#pragma config (\w+) = (\w+)", src.read_text(), re.M)
        asm = (tmp_path / str(k) / "config_xc8.asm").read_text()
        assert sorted(re.findall(r"^\s*CONFIG\s+(\w+)=(\w+)", asm, re.M)) == sorted(pragmas)
        assert len(pragmas) >= 20 and len({n for n, _ in pragmas}) == len(pragmas)   # each setting once


def test_a_wrong_config_value_is_refused(device, tmp_path):
    bad = tmp_path / "config_xc8.c"
    text = (COMMITTED / "config_xc8.c").read_text()
    assert "#pragma config OSC = HSPLL " in text
    bad.write_text(text.replace("#pragma config OSC = HSPLL ", "#pragma config OSC = HSPLLX "))
    r = _sdcc(device, bad, tmp_path / "out")
    assert r.returncode != 0 and "HSPLLX" in r.stdout + r.stderr


def test_main_xc8_compiles_against_the_register_shim(folders):
    for folder in folders:
        r = _gcc(folder, folder / "main_xc8.c")
        assert r.returncode == 0, r.stderr
        r = _gcc(folder, folder / "config_xc8.c")
        assert r.returncode == 0, r.stderr


def test_main_xc8_calling_a_missing_entry_point_fails(tmp_path):
    text = (COMMITTED / "main_xc8.c").read_text()
    assert "fw_poll();" in text
    bad = tmp_path / "main_xc8.c"
    bad.write_text(text.replace("fw_poll();", "fw_pol();"))
    r = _gcc(COMMITTED, bad)
    assert r.returncode != 0 and "fw_pol" in r.stderr
