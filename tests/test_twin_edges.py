"""The chip at the edges, on the bundled firmware: a hung program (the hardware watchdog), a
replayed host frame (the link watchdog), a noisy line (the receive path).  The processor-twin
cases run the real HEX on the PIC18 core (picdrive.firmware.target.build_measured of
firmware_build/duy2008); the link cases run on the software twin (the same C on the host) too.
Everything in simulated time."""
from __future__ import annotations

import random

import pytest

from picdrive.firmware import p18f4431, target
from picdrive.link import codec
from picdrive.link import protocol as P
from picdrive.paths import firmware_build_dir
from picdrive_hil.twin import Twin
from support.twin_uart import command
from test_twin_pil_firmware import link_id_scale

FW = firmware_build_dir() / "duy2008"
WDT_S = 0.032            # the firmware's watchdog: CONFIG2H WDPS 1:8 x 4 ms (codegen.WDT_MS)


@pytest.fixture(scope="module")
def build(tmp_path_factory):
    return target.build_measured(FW, tmp_path_factory.mktemp("edges-hex"))


def make(kind: str, build) -> Twin:
    if kind == "pil":
        return Twin("duy2008", FW, hex_file=build.hex_path, enlarged_memory=not build.on_chip, seed=0)
    return Twin("duy2008", FW, seed=0)


def running(tw, rpm: float = 1500.0, link_timeout_ms: int = 60000) -> None:
    tw.run(0.01)
    lt_id, _ = link_id_scale("link_timeout")
    _, sp_scale = link_id_scale("speed_setpoint")
    command(tw, "param_set", 1, {"id": lt_id, "value": link_timeout_ms})
    command(tw, "set_speed", 2, {"value": int(round(rpm / sp_scale))})
    command(tw, "start", 3)
    for seq in (4, 5, 6):                                # up to speed, the link watchdog fed
        tw.run(0.1)
        command(tw, "heartbeat", seq)
    assert tw.state()["outputs_active"]


# ---------------------------------------------------------------- the link watchdog

@pytest.mark.parametrize("cmd", ["heartbeat", "status"])   # a stored reply; a read-only command run again
@pytest.mark.parametrize("kind", ["sil", "pil"])
def test_a_replayed_frame_is_answered_but_does_not_feed_the_link_watchdog(kind, cmd, build):
    """One identical host frame every 100 ms (a stuck host, a loop-back replaying the last
    frame) must not keep the motor running: the watchdog stops it link_timeout after the last
    new command, and each replay is still answered.  Fresh frames at the same rate do keep it
    running (the control)."""
    tw = make(kind, build)
    running(tw, link_timeout_ms=300)
    dec = codec.StreamDecoder()
    for k in range(8):                                   # fresh frames: a new SEQ each
        tw.uart_write(codec.encode_command(cmd, 0x40 + k))
        tw.run(0.1)
    assert tw.state()["outputs_active"]
    frame = codec.encode_command(cmd, 0x60)
    t_first = tw.t
    answers = 0
    for _ in range(10):                                  # the same frame, 1 s
        tw.uart_write(frame)
        tw.run(0.1)
        answers += sum(1 for f in dec.feed(tw.uart_read()) if f.is_reply and f.is_ack and f.seq == 0x60)
    s = tw.state()
    assert not s["outputs_active"], "a replayed frame kept the motor running"
    t_off = s["outputs_off_t_s"]
    print(f"{kind}: outputs off {1e3 * (t_off - t_first):.1f} ms after the first of the replayed frames "
          f"(link_timeout 300 ms); {answers} of 10 answered")
    assert t_off - t_first <= 0.3 + 0.01
    assert answers == 10
    st = command(tw, "status", 0x70)
    assert st["state"] == P.State.FAULT and st["fault"] == P.Fault.LINK_LOST


# ---------------------------------------------------------------- receive on a noisy line

def _candidate(rng: random.Random) -> bytes:
    """A frame the board rejects at its CRC: a command frame 16..46 B long with one byte of its
    body changed (never to 0x00), then its delimiter."""
    n = rng.randint(16, P.MAX_FRAME) - 7                 # COBS code, LEN TYPE SEQ, CRC, delimiter
    payload = bytes(rng.randint(1, 255) for _ in range(max(0, n)))
    f = bytearray(codec.encode_frame(rng.choice([c.code for c in P.COMMANDS]), rng.randint(0, 255), payload))
    k = rng.randint(1, len(f) - 2)
    f[k] = (f[k] + rng.randint(1, 253)) % 255 + 1       # 1..255, never itself
    return bytes(f)


@pytest.mark.parametrize("kind", ["sil", "pil"])
def test_a_noisy_line_loses_no_valid_command(kind, build):
    """Random corrupted candidates (16 B and longer, rejected at their CRC) sent right before each
    valid command, at line rate, while the drive runs: every command is answered the first time,
    no byte is lost to a receive overflow, and every candidate is counted as a bad frame."""
    tw = make(kind, build)
    running(tw, rpm=2000.0)
    rng = random.Random(24)
    dec = codec.StreamDecoder()
    n, lost, bad = 400, [], 0
    for k in range(n):
        junk = b"".join(_candidate(rng) for _ in range(rng.randint(1, 3)))
        bad += junk.count(0)
        seq = k & 0xFF
        tw.uart_write(junk + codec.encode_command("heartbeat", seq))
        t_end = tw.t + (len(junk) + 8) * 87e-6 + 0.01
        got = False
        while tw.t < t_end and not got:
            tw.run(1e-3)
            got = any(f.is_reply and f.is_ack and f.seq == seq for f in dec.feed(tw.uart_read()))
        if not got:
            lost.append(k)
    st = command(tw, "status", 0x99)
    print(f"{kind}: {n} valid commands after {bad} corrupted candidates: {len(lost)} lost; "
          f"rx_overflows {st['rx_overflows']}, crc_errors {st['crc_errors']}")
    assert lost == [] and st["rx_overflows"] == 0
    assert st["crc_errors"] >= bad                      # each candidate judged (none lost, none accepted)
    assert tw.state()["outputs_active"]


# ---------------------------------------------------------------- the hardware watchdog

def _instr(op: str, reg: str, bit: str) -> int:
    """BCF/BSF of an SFR bit in the access bank, by the .inc's names."""
    addr, pos = p18f4431.registers()[reg], p18f4431.bits()[reg][bit]
    return {"BCF": 0x9000, "BSF": 0x8000}[op] | (pos << 9) | (addr & 0xFF)


def _bra_back(words: int) -> int:
    """BRA to the instruction ``words`` words before it (1: to itself)."""
    return 0xD000 | (-words & 0x7FF)


def _goto(k: int) -> tuple[int, int]:
    return 0xEF00 | ((k >> 1) & 0xFF), 0xF000 | ((k >> 9) & 0xFFF)


def _words(*ws: int) -> bytes:
    return b"".join(bytes([w & 0xFF, w >> 8]) for w in ws)


def test_the_bundled_hex_runs_with_the_hardware_watchdog_on_and_never_resets(build):
    """CONFIG2H: WDTEN on, 1:8 (32 ms).  A healthy run never times out: idle, an EEPROM save (the
    main loop waits ~4 ms a byte), the motor running with host traffic."""
    from picdrive_hil import pil
    cfg = pil.load_image(build.hex_path, enlarged=not build.on_chip).config
    assert cfg[3] & 1 and 4 << ((cfg[3] >> 1) & 0x0F) == 32, f"CONFIG2H = 0x{cfg[3]:02X}"
    tw = make("pil", build)
    tw.run(0.05)
    command(tw, "eeprom_save", 9, limit_s=2.0)
    running(tw, rpm=2400.0)
    for k in range(100):
        tw.uart_write(codec.encode_command("status", 0x10 + k))
        tw.run(0.01)
        tw.uart_read()
    r = tw.processor_report()
    print("\n".join(r.lines()))
    assert r.wdt_period == 320_000 and r.wdt_resets == 0
    assert r.speed_gap_max < 1.1 * r.speed_period_cycles and not r.speed_stopped
    assert tw.state()["outputs_active"]


@pytest.mark.parametrize("hang", ["main loop spins", "interrupts off", "speed loop off"])
def test_a_hung_program_turns_the_outputs_off_within_the_watchdog_period(build, hang):
    """The running program is changed under it (the processor twin's flash patched at an
    instant): the main loop spinning in place (the interrupts still run: the speed loop keeps
    the bridge switching), the main loop spinning with the interrupts off (the bridge frozen
    in its last state), or the speed-loop interrupt disabled with the main loop healthy.  Each
    time the watchdog resets the chip within its period: the outputs go off, and the report
    says the chip was reset and, for the last two, that the speed-loop interrupt stopped."""
    tw = make("pil", build)
    running(tw, rpm=1500.0)
    poll = build.functions["_fw_poll"].address
    if hang == "main loop spins":
        patch = _words(_bra_back(1))
    elif hang == "interrupts off":
        # a loop (a return into fw_poll lands in it, whichever of its words that is)
        patch = _words(_instr("BCF", "INTCON", "GIEH"), _instr("BCF", "INTCON", "GIEL"), _bra_back(3))
    else:
        # TMR2IE off at every pass, then the pass as before: fw_poll's first two words move to a
        # trampoline past the program (checked not PC-relative)
        from picdrive_hil import pil
        img = pil.load_image(build.hex_path, enlarged=not build.on_chip)
        head = bytes(img.flash[poll:poll + 4])
        for w in (head[0] | head[1] << 8, head[2] | head[3] << 8):
            assert (w & 0xF000) != 0xD000 and (w & 0xF800) != 0xE000, f"fw_poll starts with a relative branch 0x{w:04X}"
        tramp = (img.flash_top + 0x40) & ~1
        tw.patch_flash(tramp, _words(_instr("BCF", "PIE1", "TMR2IE")) + head + _words(*_goto(poll + 4)))
        patch = _words(*_goto(tramp))
    t0 = tw.t
    resets0 = tw.pil_stats().wdt_resets
    tw.patch_flash(poll, patch)
    tw.run(0.02)
    mid = tw.processor_report()
    if hang != "main loop spins":
        assert mid.speed_stopped, "\n".join(mid.lines())
    tw.run(0.1)
    s, r = tw.state(), tw.processor_report()
    off = s["outputs_off_t_s"]
    print(f"{hang}: " + ("outputs still on" if s["outputs_active"] or off is None
                         else f"outputs off {1e3 * (off - t0):.1f} ms after the hang") + "\n" + "\n".join(r.lines()))
    assert not s["outputs_active"], "the hung program kept the outputs on"
    assert r.wdt_resets > resets0
    assert s["outputs_off_t_s"] - t0 <= WDT_S + 0.002
    assert any("time-out reset" in ln for ln in r.lines())
