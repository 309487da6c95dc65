"""The link module as the PIC18 compiler sees it (SDCC 4.2.0 pic16, installed by
scripts/pic_toolchain.sh), and the interrupt-safety rules it must keep there (hazards a, b
and g of docs/firmware.md's chip-only hazards table).  Cycle and flash figures are printed by bench/link_pic18.py, not asserted here."""
import re

import pytest

from linksupport import build
from picdrive.link import protocol as P

ISR_ENTRIES = ("_link_rx_byte", "_link_tick_ms", "_link_sample")


@pytest.fixture(scope="module")
def asm(tmp_path_factory):
    return build.sdcc_asm(build.render(), tmp_path_factory.mktemp("sdcc"))


def _bodies(asm: str) -> dict[str, str]:
    out, cur = {}, None
    for line in asm.splitlines():
        m = re.match(r"^(_\w+):", line)
        if m and not re.match(r"^_\d+_DS_", line):
            cur = m.group(1)
            out[cur] = ""
        elif cur is not None:
            out[cur] += line + "\n"
    return out


def test_interrupt_paths_call_no_compiler_helper(asm):
    """Hazard b: the compiler's multiply/divide/generic-pointer helpers keep their operands in
    static RAM; one reachable from an interrupt and from the main loop can be corrupted.  The
    functions the interrupts call reach no helper at all (only the application's callbacks)."""
    graph = build.asm_call_graph(asm)
    isr = build.reachable(graph, ISR_ENTRIES)
    assert set(ISR_ENTRIES) <= isr
    helpers = sorted(f for f in isr if f.startswith("__"))
    assert helpers == [], f"runtime-library helpers reachable from an interrupt: {helpers}"
    assert {"_capture_due", "_capture_done", "_put_signals", "_app_signal"} <= isr   # the graph follows the calls
    # and the main loop's products are gone too: no multiply or divide helper anywhere
    assert not re.search(r"CALL\s+__(mul|div|mod)\w+", asm)


def test_interrupt_paths_read_no_flash_table(asm):
    """Hazard a: an interrupt prologue need not save TBLPTR/TABLAT; the functions the interrupts
    call read no flash (no TBLRD, no generic-pointer read), except where the function itself saves
    the four table registers before its first table access and restores them at its only return
    (put_signals' table of signal addresses)."""
    graph, bodies = build.asm_call_graph(asm), _bodies(asm)
    table_regs = ["_TBLPTRU", "_TBLPTRH", "_TBLPTRL", "_TABLAT"]
    saving = []
    for f in build.reachable(graph, ISR_ENTRIES):
        if f not in bodies:
            continue
        code = [" ".join(ln.split(";")[0].replace(",", " ").split()) for ln in bodies[f].splitlines()]
        code = [c for c in code if c and not c.endswith(":")]
        code = code[:max(i for i, c in enumerate(code) if c.startswith(("RETURN", "RETFIE"))) + 1]
        touches = [i for i, c in enumerate(code) if "TBLRD" in c or "TBLPTR" in c or "TABLAT" in c
                   or any(r in c.split()[1:] for r in table_regs)]
        if not touches:
            continue
        saving.append(f)
        assert code[:4] == [f"MOVFF {r} _POSTDEC1" for r in table_regs], f     # pushed first
        assert code[-5:] == [f"MOVFF _PREINC1 {r}" for r in reversed(table_regs)] + ["RETURN"], f
        assert sum(c.startswith(("RETURN", "RETFIE")) for c in code) == 1, f  # no other way out
        assert not any(c.startswith(("GOTO", "BRA")) and c.split()[1].startswith("_") for c in code), f
    assert saving == ["_put_signals"]


def test_rx_interrupt_shares_single_bytes_only():
    """Hazard g: state written by link_rx_byte (high-priority interrupt) is read by the main
    loop under a guard that may mask only the low priority: every variable it writes is one
    byte (the frame buffer's fill count, the ready flag, the lost-byte count, the spill ring's
    write index) or a byte of the frame buffer or of the spill ring, indexed by a byte."""
    c = build.render()["link_fw.c"]
    hot = re.search(r"struct link_fast \{(.*?)\n\} link_hot;", c, re.S).group(1)
    fields = dict((name, t) for t, name in re.findall(r"^\s+(?:volatile )?(u?int\d+_t) (\w+);", hot, re.M))
    fields.update((name, t) for t, name in re.findall(r"^static volatile (u?int\d+_t) (rx_sp_[wr]);", c, re.M))
    asm, body = re.findall(r"void link_rx_byte\(uint8_t b\)[^{]*\{(.*?)\n\}", c, re.S)
    local = set(re.findall(r"^\s+uint8_t (\w+) =", body, re.M))
    written = set(re.findall(r"\b(\w+)\s*(?:=[^=]|\+\+|--|\+=|-=)", body)) - {"rx_buf", "rx_spill"} - local
    written |= set(re.findall(r"(?:\+\+|--)(\w+)", body))
    assert written == {"rx_n", "rx_ready", "rx_ovf", "rx_sp_w"}, written
    assert {f: fields[f] for f in written | {"rx_sp_r"}} == {f: "uint8_t" for f in written | {"rx_sp_r"}}
    assert "S." not in body                                  # nothing of the main loop's state
    assert re.search(r"rx_buf\[rx_n\] = b;", body) and P.RX_BUFFER_BYTES < 256
    assert re.search(r"rx_spill\[rx_sp_w\] = b;", body) and P.RX_SPILL_BYTES < 256
    # the PIC18 assembly form (SDCC) writes the same bytes (link_hot's rx_n, rx_ready, rx_ovf,
    # first in the block; rx_sp_w), the buffers through FSR0 + W (PLUSW0) and PRODL/PRODH
    # (saved by the interrupt prologue)
    assert list(fields)[:3] == ["rx_n", "rx_ready", "rx_ovf"]
    targets = set(re.findall(r"^\s*(?:MOVWF|CLRF|SETF)\s+(\(_link_hot \+ LH_\w+\)|\w+)", asm, re.M))
    targets |= set(re.findall(r"^\s*(?:INCF|DECF)\s+(\(_link_hot \+ LH_\w+\)|\w+),\s*F", asm, re.M))
    targets |= set(re.findall(r"^\s*MOVFF\s+\w+,\s*(\w+)", asm, re.M))
    assert targets == {"(_link_hot + LH_RX_N)", "(_link_hot + LH_RX_READY)", "(_link_hot + LH_RX_OVF)", "_PRODL",
                       "_rx_sp_w", "_PLUSW0", "_PRODH"}, targets
    assert re.search(r"LFSR\s+0,\s*_rx_buf", asm) and re.search(r"LFSR\s+0,\s*_rx_spill", asm) and "__asm" in asm


def _bench():
    import importlib.util
    from pathlib import Path
    path = Path(__file__).resolve().parents[1] / "bench" / "link_pic18.py"
    spec = importlib.util.spec_from_file_location("link_pic18", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _host_exchange(files, frames, after=None) -> bytes:
    """What the host build (linksupport's fake board, gcc) sends: its boot bytes, then its bytes after
    each frame; ``after(board)`` runs on the board before it closes."""
    from linksupport.fakeboard import FakeBoard
    b = FakeBoard(files=files, txq_bytes=4096)
    try:
        b.boot()
        host = b.take_tx()
        for f in frames:
            b.feed(f)
            host += b.take_tx()
        if after is not None:
            after(b)
    finally:
        b.close()
    return host


def test_the_chip_answers_byte_for_byte_like_the_host_build():
    """The module on the PIC18 core (gpsim, with its assembly RX byte path and CRC) and its host
    build (gcc) get the same frames byte by byte and send the same bytes back: replies, NACKs
    (malformed, unknown, bad CRC), a duplicate replayed, a frame lost to a waiting one, garbage
    and the EEPROM image written and read back."""
    from picdrive.link import codec
    files = build.render()
    cmd = codec.encode_command
    frames = [cmd("hello", 1), cmd("param_get", 2, {"ids": [0x00, 0x04, 0x07, 0x41]}),
              cmd("param_info", 3, {"index": 6}), cmd("param_set", 4, {"id": 0x07, "value": 1000}),
              cmd("param_set", 4, {"id": 0x07, "value": 1000}),                      # duplicate: replayed
              cmd("param_set", 5, {"id": 0x07, "value": 70000}),                     # out of range
              codec.encode_frame(0x3E, 6, b"", lead=True),                           # unknown command
              codec.encode_frame(P.COMMAND_BY_NAME["hello"].code, 7, b"\x01", lead=True),   # malformed
              bytes([0x00, 0x05, 0x11, 0x22, 0x33, 0x44, 0x00]),                     # bad CRC: one NACK
              cmd("eeprom_save", 8), cmd("param_set", 9, {"id": 0x07, "value": 5}), cmd("eeprom_load", 10),
              cmd("param_get", 11, {"ids": [0x07]}), bytes([0x01] * 60) + b"\x00", cmd("status", 12)]
    bench = _bench()
    chip = bench.chip_exchange(files["link_fw.c"], files["link_fw.h"], frames)
    host_i16 = {}
    host = _host_exchange(files, frames, after=lambda b: host_i16.update(
        {i: b.lib.link_param_i16(i) for i in bench.I16_IDS}))
    # link_param_i16 (the assembly's saturation on the chip): the same for every parameter id,
    # 0 for unknown ids, the harness's values for the signals
    sig_index = {e.id: i for i, e in enumerate(t for t in P.build_table(2) if t.signal)}
    want = {i: _signal(sig_index[i]) if i in sig_index else v for i, v in host_i16.items()}
    assert bench.chip_exchange.param_i16 == want
    assert any(v == 32767 for v in want.values()) and 0 in want.values()    # saturated ones and unknown ids
    dec_chip, dec_host = codec.StreamDecoder().feed(chip), codec.StreamDecoder().feed(host)
    assert len(dec_chip) == len(frames)                # BOOT, one reply each (the bad CRC: one NACK), garbage silent
    # the BOOT event's code is the application's (the fake board reports its own reset cause)
    assert dec_chip[1:] == dec_host[1:] and dec_chip[0].type == P.MSG_EVENT
    status_chip, status_host = (codec.decode_reply("status", d[-1].payload) for d in (dec_chip, dec_host))
    assert status_chip["crc_errors"] == 1 and status_chip == status_host


def _signal(i: int) -> int:
    """app_signal(i) of bench/link_pic18.py's chip harness."""
    return ((0x0101 * i - 0x3000 + 0x8000) & 0xFFFF) - 0x8000 if i < 7 else 0


@pytest.mark.parametrize("cap_mask", [0b1011, 0b10110])
def test_telemetry_and_capture_on_the_chip(cap_mask):
    """link_sample on the PIC18 core: telemetry frames and a capture recorded in the same samples
    (the same mask as the telemetry, or another), each signal value where the protocol puts it."""
    from picdrive.link import codec
    files = build.render()
    cmd = codec.encode_command
    tel_mask = 0b1011
    frames = [cmd("telem_config", 1, {"mask": tel_mask, "decimation": 1, "samples_per_frame": 2}),
              cmd("capture_arm", 2, {"mask": cap_mask, "n_samples": 5, "pre_trigger": 0, "decimation": 2,
                                     "trigger": P.Trigger.IMMEDIATE, "threshold": 0}),
              cmd("capture_read", 3, {"start": 1, "count": 10}), cmd("param_get", 4, {"ids": [0x20, 0x23]})]
    chip = _bench().chip_exchange(files["link_fw.c"], files["link_fw.h"], frames, [0, 12, 0, 0])
    got = codec.StreamDecoder().feed(chip)
    tel = [f for f in got if f.type == P.MSG_TELEMETRY]
    nt = bin(tel_mask).count("1")
    want = [_signal(i) for i in range(16) if tel_mask >> i & 1]
    counters = []
    for f in tel:
        counter, vals = codec.decode_telemetry(f.payload, nt)
        counters.append(counter)
        assert vals.shape == (2, nt) and (vals == want).all()
    assert counters == list(range(0, 12, 2))
    r = codec.decode_reply("capture_read", [f for f in got if f.is_reply and f.seq == 3][0].payload)
    cap = [_signal(i) for i in range(16) if cap_mask >> i & 1]
    assert r["state"] == P.CaptureState.DONE and r["total"] == 5 and r["start"] == 1
    assert r["values"] == cap * 4
    r = codec.decode_reply("param_get", [f for f in got if f.is_reply and f.seq == 4][0].payload)
    assert r["values"] == [_signal(0), _signal(3)]            # signals through app_signal, sign-extended


@pytest.mark.parametrize("trigger,ramp,thr", [(P.Trigger.SPEED_RISING, 0x100, -0x2C00),
                                              (P.Trigger.SPEED_FALLING, -0x100, -0x3300),
                                              (P.Trigger.SPEED_RISING, 0x5000, -0x4800)])   # differences beyond int16
def test_capture_threshold_trigger_on_the_chip(trigger, ramp, thr):
    """The speed-crossing trigger of the assembly capture on the PIC18 core: the speed (signal 0)
    moves by ``ramp`` a sample; the record holds the pre-trigger samples and the samples from the
    first crossing on, as the protocol defines them (signed int16 compare, falling = the
    complements rising)."""
    from picdrive.link import codec
    files = build.render()
    n, pre, samples = 6, 2, 20
    frames = [codec.encode_command("capture_arm", 1, {"mask": 1, "n_samples": n, "pre_trigger": pre, "decimation": 1,
                                                      "trigger": trigger, "threshold": thr}),
              codec.encode_command("capture_read", 2, {"start": 0, "count": 10})]
    reads = [(2, 3), (5, 10), (6, 4), (0, 0)]                 # (start, count): parts, the end, nothing
    frames += [codec.encode_command("capture_read", 3 + k, {"start": a, "count": c}) for k, (a, c) in enumerate(reads)]
    frames += [codec.encode_command("capture_read", 9, {"start": 7, "count": 1}),        # beyond the record
               codec.encode_command("capture_read", 10, {"start": 256, "count": 1})]
    chip = _bench().chip_exchange(files["link_fw.c"], files["link_fw.h"], frames, [samples] + [0] * 7, ramp=ramp)
    v = [((_signal(0) + k * ramp + 0x8000) & 0xFFFF) - 0x8000 for k in range(samples)]
    flip = (lambda x: ~x) if trigger == P.Trigger.SPEED_FALLING else (lambda x: x)
    fire = next(k for k in range(1, samples) if flip(v[k - 1]) < flip(thr) <= flip(v[k]))
    got = {f.seq: f for f in codec.StreamDecoder().feed(chip) if f.is_reply or f.type == P.MSG_NACK}
    r = codec.decode_reply("capture_read", got[2].payload)
    assert r["state"] == P.CaptureState.DONE and r["total"] == n and r["trigger_index"] == pre
    record = v[fire - pre:fire - pre + n]
    assert r["values"] == record
    for k, (a, c) in enumerate(reads):
        r = codec.decode_reply("capture_read", got[3 + k].payload)
        assert r["start"] == a and r["values"] == record[a:a + c]
    assert [got[q].type == P.MSG_NACK and got[q].payload[1] == P.Nack.OUT_OF_RANGE for q in (9, 10)] == [True, True]


def test_capture_arm_checks_on_the_chip():
    """capture_arm's argument checks (the assembly on the PIC18 core) give the host build's
    replies: every NACK reason and the largest record that fits."""
    from picdrive.link import codec
    files = build.render()
    T = P.Trigger
    bad = [dict(mask=0), dict(mask=0x8001), dict(n_samples=0), dict(n_samples=P.CAPTURE_BYTES_DEFAULT // 2 + 1),
           dict(n_samples=0x101), dict(pre_trigger=0x100), dict(pre_trigger=8, n_samples=8), dict(decimation=0),
           dict(trigger=4), dict(trigger=T.IMMEDIATE, pre_trigger=1), dict(mask=0x7FF, n_samples=P.CAPTURE_BYTES_DEFAULT // 22 + 1),
           dict(mask=0x7FF, n_samples=P.CAPTURE_BYTES_DEFAULT // 22), dict(mask=0x3, n_samples=32, trigger=T.SPEED_FALLING, threshold=-5)]
    base = dict(mask=0x3, n_samples=8, pre_trigger=2, decimation=1, trigger=T.SETPOINT_CHANGE, threshold=0)
    frames = [codec.encode_command("capture_arm", k + 1, {**base, **d}) for k, d in enumerate(bad)]
    frames.append(codec.encode_command("capture_read", 40, {"start": 0, "count": 1}))
    chip = _bench().chip_exchange(files["link_fw.c"], files["link_fw.h"], frames)
    host = _host_exchange(files, frames)
    dec_chip, dec_host = codec.StreamDecoder().feed(chip), codec.StreamDecoder().feed(host)
    assert dec_chip[1:] == dec_host[1:] and len(dec_chip) == len(frames) + 1
    nacks = [f for f in dec_chip if f.type == P.MSG_NACK and f.seq <= len(bad)]
    assert len(nacks) == 11 and all(f.payload[1] == P.Nack.OUT_OF_RANGE for f in nacks)


def test_telem_config_checks_on_the_chip():
    """telem_config (the assembly on the PIC18 core) gives the host build's replies: the frame
    length, 0 when off, and OUT_OF_RANGE for an empty or foreign mask, no samples, too long a frame."""
    from picdrive.link import codec
    files = build.render()
    cases = [(0xF, 1, 4), (0xF, 0, 0), (0x8000, 0, 9), (0, 1, 1), (0x8001, 1, 1), (0x3, 1, 0), (0xF, 1, 5),
             (0xF, 2, 4), (0x7FF, 3, 1), (0x7FF, 1, 2)]
    frames = [codec.encode_command("telem_config", k + 1, {"mask": m, "decimation": d, "samples_per_frame": n})
              for k, (m, d, n) in enumerate(cases)]
    chip = _bench().chip_exchange(files["link_fw.c"], files["link_fw.h"], frames)
    host = _host_exchange(files, frames)
    dec_chip, dec_host = codec.StreamDecoder().feed(chip), codec.StreamDecoder().feed(host)
    assert dec_chip[1:] == dec_host[1:] and len(dec_chip) == len(frames) + 1
    assert [f.type == P.MSG_NACK for f in dec_chip[1:]] == [False, False, False, True, True, True, True, False,
                                                            False, True]


def test_param_get_checks_on_the_chip():
    """param_get (the assembly on the PIC18 core): the host build's replies for no id, too many,
    an unknown one among known ones, and the most ids with signals among them."""
    from picdrive.link import codec
    files = build.render()
    ids = [e.id for e in P.build_table(2).entries if not e.signal]
    frames = [codec.encode_frame(P.COMMAND_BY_NAME["param_get"].code, 1, b"", lead=True),
              codec.encode_command("param_get", 2, {"ids": ids[:P.PARAM_GET_MAX]}),
              codec.encode_frame(P.COMMAND_BY_NAME["param_get"].code, 3, bytes(ids[:P.PARAM_GET_MAX + 1]), lead=True),
              codec.encode_command("param_get", 4, {"ids": [ids[0], 0x30, ids[1]]}),
              codec.encode_command("param_get", 5, {"ids": [e.id for e in P.build_table(2).entries][-P.PARAM_GET_MAX - 4:-4]})]
    chip = _bench().chip_exchange(files["link_fw.c"], files["link_fw.h"], frames)
    host = _host_exchange(files, frames)
    dec_chip, dec_host = codec.StreamDecoder().feed(chip), codec.StreamDecoder().feed(host)
    assert dec_chip[1:5] == dec_host[1:5] and len(dec_chip) == len(dec_host) == len(frames) + 1
    assert [f.type == P.MSG_NACK for f in dec_chip[1:]] == [True, False, True, True, False]
    assert len(dec_chip[2].payload) == len(dec_chip[5].payload) == 4 * P.PARAM_GET_MAX
    # the last mixes signals (the harness's values on the chip, the fake drive's on the host)
    entries = P.build_table(2).entries[-P.PARAM_GET_MAX - 4:-4]
    sig_index = {e.id: i for i, e in enumerate(t for t in P.build_table(2) if t.signal)}
    chip_v = codec.decode_reply("param_get", dec_chip[5].payload)["values"]
    host_v = codec.decode_reply("param_get", dec_host[5].payload)["values"]
    assert any(e.signal for e in entries) and any(not e.signal for e in entries)
    assert chip_v == [_signal(sig_index[e.id]) if e.signal else h for e, h in zip(entries, host_v)]


def test_small_tx_room_on_the_chip():
    """With a UART queue reporting 3 free bytes (tx_drain's room running out on every poll), the
    chip still sends every frame whole and in order: the host build's bytes."""
    from picdrive.link import codec
    files = build.render()
    frames = [codec.encode_command("hello", 1), codec.encode_command("param_get", 2, {"ids": [0x00, 0x07]}),
              codec.encode_command("status", 3)]
    chip = _bench().chip_exchange(files["link_fw.c"], files["link_fw.h"], frames, [40, 40, 40], tx_room=3)
    host = _host_exchange(files, frames)
    dec_chip, dec_host = codec.StreamDecoder().feed(chip), codec.StreamDecoder().feed(host)
    assert len(dec_chip) == len(frames) + 1
    assert dec_chip[1:3] == dec_host[1:3]                       # hello, param_get (status: uptime differs)
    assert dec_chip[3].seq == 3 and dec_chip[3].is_reply


def test_assembly_leaves_the_frame_pointer_alone():
    """The module's assembly runs with interrupts enabled: an interrupt function that sets up a
    frame saves only FSR2L (SDCC's small stack model keeps the stack in one bank), so FSR2H must
    never change under it (a main-loop copy through FSR2 once corrupted the speed loop's
    arguments: an overspeed trip under UART traffic).  No FSR2 in the assembly at all."""
    c = build.render()["link_fw.c"]
    blocks = re.findall(r"__asm(.*?)__endasm", c, re.S)
    assert len(blocks) >= 10
    code = "\n".join(ln.split(";")[0] for b in blocks for ln in b.splitlines())
    assert not re.search(r"0xFD[9A-F]\b|LFSR\s+2\b|FSR2|INDF2|PLUSW2|POSTINC2|POSTDEC2|PREINC2", code, re.I)
