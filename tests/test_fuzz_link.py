"""Fuzzing the C receiver and dispatcher under AddressSanitizer + UndefinedBehaviorSanitizer.

The harness (tests/linksupport/fuzz_main.c) checks the module against an independent
reference decoder, the resync bound, bit-flip rejection and one reply per accepted frame; see
its header.  CI runs 3 x 10^6 bytes (well under a second each); bench/fuzz_link.py runs more.
"""
import math
import subprocess

import pytest

from linksupport import build


def run_fuzz(exe, nbytes, seed):
    r = subprocess.run([str(exe), "--bytes", str(nbytes), "--seed", str(seed)], capture_output=True, text=True,
                       timeout=120)
    figures = dict(line.split("=", 1) for line in r.stdout.splitlines() if "=" in line)
    return r, figures


@pytest.fixture(scope="module")
def fuzz_exe():
    return build.fuzz_executable()


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_fuzz_one_million_bytes_under_sanitizers(fuzz_exe, seed):
    r, f = run_fuzz(fuzz_exe, 1_000_000, seed)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-4000:]
    assert f["OK"] == "1" and "FAIL" not in f
    assert int(f["bytes"]) == 1_000_000
    # the run exercised what it claims to
    assert int(f["intact"]) > 10_000 and int(f["intact_accepted"]) >= int(f["intact"]) - 20
    assert int(f["flipped_rejected"]) > 3_000
    assert int(f["crc_failures"]) > 10_000 and int(f["out_badcrc_nacks"]) > 1_000
    assert int(f["out_telemetry"]) > 100                       # telemetry path ran under the sanitizers
    assert int(f["max_accept_bytes_after_frame_end"]) <= int(f["resync_bound_bytes"])
    # frames accepted by chance have the 2^-16 rate of a 16-bit CRC (Poisson, generous bound)
    lam = float(f["chance_expected"])
    assert int(f["chance_crc_frames"]) <= lam + 6 * math.sqrt(lam) + 3


def _mutant(old: str, new: str):
    files = build.render()
    assert old in files["link_fw.c"], old
    files["link_fw.c"] = files["link_fw.c"].replace(old, new, 1)
    return build.fuzz_executable(files)


def test_harness_catches_a_buffer_overflow():
    """A receive ring whose write index wraps at 128 instead of 64 writes past the ring:
    the sanitizers stop the run (UBSan's bounds check or ASan: they are really on)."""
    exe = _mutant("uint8_t next = (uint8_t)((uint8_t)(S.rx_head + 1u) & RX_MASK);",
                  "uint8_t next = (uint8_t)((uint8_t)(S.rx_head + 1u) & 0x7Fu);")
    r, f = run_fuzz(exe, 200_000, 1)
    assert r.returncode != 0 and "FAIL" not in f
    assert "index 64 out of bounds for type 'uint8_t [64]'" in r.stderr or "global-buffer-overflow" in r.stderr


def test_harness_catches_a_crc_check_hole():
    """A receiver that skips the CRC of empty frames is caught by the reference comparison."""
    exe = _mutant("if (crc != got) {", "if (crc != got && len != 0u) {")
    r, f = run_fuzz(exe, 200_000, 1)
    assert r.returncode == 1 and "FAIL" in f


def test_harness_catches_a_wrong_resync():
    """A receiver that skips the whole candidate after a bad CRC (instead of only the SOF)
    loses frames that follow garbage: caught."""
    exe = _mutant("            rx_drop(1u);\n            continue;\n        }\n        for (i = 1u;",
                  "            rx_drop(need);\n            continue;\n        }\n        for (i = 1u;")
    r, f = run_fuzz(exe, 200_000, 1)
    assert r.returncode == 1 and "FAIL" in f
