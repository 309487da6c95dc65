"""Fuzzing the C receiver and dispatcher under AddressSanitizer + UndefinedBehaviorSanitizer,
and the three defects of the 1.x framing (start byte, no stuffing), each with a test that fails
on it.

The harness (tests/linksupport/fuzz_main.c) checks the module against an independent
reference decoder, acceptance of every intact frame sent after a delimiter and one reply per
accepted command, and counts false accepts per kind of corruption; see its header.  CI runs
3 x 10^6 bytes; bench/fuzz_link.py runs >= 10^7.
"""
import math
import subprocess

import pytest

from linksupport import build
from linksupport.fakeboard import FakeBoard
from picdrive.link import codec, protocol as P

KINDS = ("garbage", "nested", "truncated", "badlen", "flipped", "insdel")


def run_fuzz(exe, nbytes, seed):
    r = subprocess.run([str(exe), "--bytes", str(nbytes), "--seed", str(seed)], capture_output=True, text=True,
                       timeout=120)
    figures = dict(line.split("=", 1) for line in r.stdout.splitlines() if "=" in line)
    return r, figures


@pytest.fixture(scope="module")
def fuzz_exe():
    return build.fuzz_executable()


def chance_bound(candidates: int) -> float:
    """Poisson bound on the frames a CRC-16 passes by chance among corrupted candidates."""
    lam = candidates / 65536.0
    return lam + 6 * math.sqrt(lam) + 1


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_fuzz_one_million_bytes_under_sanitizers(fuzz_exe, seed):
    r, f = run_fuzz(fuzz_exe, 1_000_000, seed)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-4000:]
    assert f["OK"] == "1" and "FAIL" not in f
    assert int(f["bytes"]) == 1_000_000
    # the run exercised what it claims to
    assert int(f["intact"]) > 10_000 and int(f["intact_lead_accepted"]) == int(f["intact_lead"]) > 8_000
    for k in KINDS:
        assert int(f[f"candidates_{k}"]) > 2_000, k
        # false accepts at or below the CRC's chance rate in every kind of corruption
        assert int(f[f"false_accepts_{k}"]) <= chance_bound(int(f[f"candidates_{k}"])), k
    assert int(f["out_badcrc_nacks"]) > 1_000
    assert int(f["out_telemetry"]) > 100                       # telemetry path ran under the sanitizers


def _mutant(old: str, new: str):
    files = build.render()
    assert old in files["link_fw.c"], old
    files["link_fw.c"] = files["link_fw.c"].replace(old, new, 1)
    return build.fuzz_executable(files)


def test_harness_catches_a_buffer_overflow():
    """A receiver that lets a long candidate write one byte past the frame buffer: the
    sanitizers stop the run (UBSan's bounds check or ASan: they are really on)."""
    exe = _mutant("} else if (rx_n < LINK_RX_BYTES) {", "} else if (rx_n <= LINK_RX_BYTES) {")
    r, f = run_fuzz(exe, 200_000, 1)
    assert r.returncode != 0 and "FAIL" not in f
    n = P.RX_BUFFER_BYTES
    assert (f"index {n} out of bounds for type 'uint8_t [{n}]'" in r.stderr
            or "global-buffer-overflow" in r.stderr)


def test_harness_catches_a_crc_check_hole():
    """A receiver that skips the CRC of empty frames is caught by the reference comparison."""
    exe = _mutant("== n && (crc_hi | crc_lo) == 0u) {", "== n && ((crc_hi | crc_lo) == 0u || rx_buf[0] == 0u)) {")
    r, f = run_fuzz(exe, 200_000, 1)
    assert r.returncode == 1 and "FAIL" in f


def test_harness_catches_a_missing_length_check():
    """A receiver that ignores LEN against the decoded length is caught (by the reference
    comparison, or by a sanitizer when a handler trusts the wrong LEN)."""
    exe = _mutant("(uint8_t)(rx_buf[0] + BODY_OVERHEAD) == n && ", "")
    r, f = run_fuzz(exe, 200_000, 1)
    assert r.returncode != 0 and ("FAIL" in f or "ERROR: AddressSanitizer" in r.stderr or "runtime error" in r.stderr)


# ---- the three defects of the 1.x framing.  These use only encode_frame / encode_command /
# StreamDecoder, which both framings have, so each one fails on the 1.x module and codec. ----
@pytest.fixture(scope="module")
def board():
    b = FakeBoard(P.build_table(2), txq_bytes=4096)
    yield b
    b.close()


def _accepted(board, data: bytes) -> list[codec.Frame]:
    """Frames the C module (its dispatcher's log) and the Python decoder accept from data,
    after a fresh boot; asserts both agree."""
    board.boot()
    board.take_tx()
    board.clear_log()
    board.feed(data)
    c = [codec.Frame(t, s, p) for t, s, p, _ in board.log()]
    py = [f for f in codec.StreamDecoder().feed(data) if f.type < P.MSG_TELEMETRY]
    assert c == py
    return c


def test_a_frame_inside_a_payload_never_executes(board):
    """1.x: a frame carried in another frame's payload executed when the outer start byte was
    lost.  Lose any number of leading bytes of the outer frame: the inner one never runs."""
    inner = codec.encode_command("stop", 0x42)
    outer = codec.encode_frame(P.COMMAND_BY_NAME["param_set"].code, 0x01, inner)
    after = codec.encode_command("heartbeat", 0x43)
    for k in range(1, len(outer) - 1):
        got = _accepted(board, outer[k:] + after)
        assert codec.Frame(P.COMMAND_BY_NAME["stop"].code, 0x42) not in got, k
        assert codec.Frame(P.COMMAND_BY_NAME["heartbeat"].code, 0x43) in got, k


def test_a_frame_cut_one_byte_short_is_not_completed_by_the_next_frame(board):
    """1.x: a frame that lost its last byte was completed by the next frame's start byte when
    the lost byte (the CRC's low byte) equalled it: 1 in 256.  Over all 256 SEQs (so every
    value of the last byte) the cut frame is never accepted and the next one always is."""
    nxt = codec.encode_command("heartbeat", 0x77)
    for seq in range(256):
        data = codec.encode_frame(P.COMMAND_BY_NAME["set_speed"].code, seq, bytes((0x10, 0x27, 0, 0)))
        cut = data[:-2] if data[-1] == 0 else data[:-1]       # the last byte that carries the frame is lost
        got = _accepted(board, cut + nxt)
        assert all(f.type != P.COMMAND_BY_NAME["set_speed"].code for f in got), seq
        assert got == [codec.Frame(P.COMMAND_BY_NAME["heartbeat"].code, 0x77)], seq


def test_a_len_one_short_with_a_recomputed_crc_is_rejected(board):
    """1.x: a frame whose LEN is one short, with the CRC computed over what that LEN covers,
    was accepted (the payload's last byte was then skipped as garbage).  The frame's own length
    now checks LEN: the byte LEN leaves over is inside the frame, and the frame is dropped.
    (A leftover 0x00 would be stuffed by COBS; test_codec covers that case on the body.)"""
    for last in range(1, 256):
        payload = bytes((0x03, 0x10, 0x27, 0x00, last))         # param_set id 3 ... with a 5th byte
        short = codec.encode_frame(P.COMMAND_BY_NAME["param_set"].code, 0x21, payload[:4])
        # the leftover byte stays in the frame: before its delimiter (2.x) or after it (1.x)
        wire = short[:-1] + bytes((last,)) + short[-1:] if short[-1] == 0 else short + bytes((last,))
        got = _accepted(board, wire)
        assert got == [], last
