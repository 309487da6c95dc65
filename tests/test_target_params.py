"""drive.c's load_param and write_duty on the chip: every parameter the speed loop reads lands
in core_p, and the duty registers follow the law's output.

load_param is PIC18 assembly under SDCC (the host twin runs its C twin), so this runs the
bundled HEX on the processor twin (picdrive_hil's PIL, simulated time): each parameter is
written over the UART with param_set, then the data memory of core_p is read back (peek) and
must hold every parameter's raw value at its field (drive_core.h's core_params_t, little-endian),
the membership slope core_premise_k() of the premise bounds (picdrive.firmware.fixedpoint's
premise_k), and nothing else may change.  write_duty (assembly too) is checked at several
instants of a run in both directions.
"""
from __future__ import annotations

import re
import tempfile
import warnings
from pathlib import Path

import pytest

from picdrive.firmware import fixedpoint, target
from picdrive.link import codec
from picdrive.paths import firmware_build_dir
from picdrive.profile import ProfileWarning

FW = firmware_build_dir() / "duy2008"


def _define(text: str, name: str) -> int:
    m = re.search(rf"#define\s+{name}\s+\(?(-?(?:0x[0-9A-Fa-f]+|\d+))[uUlL]*\)?", text)
    assert m, name
    return int(m.group(1), 0)


@pytest.fixture(scope="module")
def twin(tmp_path_factory):
    from picdrive_hil.twin import Twin
    b = target.build_measured(FW, tmp_path_factory.mktemp("hex"), name="duy2008")
    _, symbols = target.parse_map((b.hex_path.with_suffix(".map")).read_text())
    core_p = next(s.address for s in symbols if s.name == "_core_p")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ProfileWarning)
        tw = Twin("duy2008", FW, hex_file=str(b.hex_path), enlarged_memory=False, seed=0)
    tw.run(0.01)
    yield tw, core_p
    tw.close()


def test_param_set_loads_each_speed_loop_parameter_into_core_p(twin):
    tw, core_p = twin
    h = (FW / "link_fw.h").read_text()
    params = (FW / "drive_params.h").read_text()
    nr = _define(params, "CORE_N_RULES")
    mu_sh = _define(params, "CORE_MU_SH")
    # core_params_t: kp[], kits[], kdts[], kc[], premise_lo, premise_hi, mu_k, b_q14, u_min, u_max,
    # controller (1 byte), ilim, accel_step
    fields = {"setpoint_weight": (8 * nr + 6, 2), "u_min": (8 * nr + 8, 2), "u_max": (8 * nr + 10, 2),
              "controller": (8 * nr + 12, 1), "current_limit": (8 * nr + 13, 2),
              "accel_limit": (8 * nr + 15, 2), "premise_low": (8 * nr, 2), "premise_high": (8 * nr + 2, 2)}
    for r in range(nr):
        for g, gain in enumerate(("kp", "ki", "kd", "kc")):
            fields[f"rule{r + 1}_{gain}"] = (2 * (g * nr + r), 2)
    size = 8 * nr + 17

    def ram():
        return bytes(tw.peek(core_p + k) for k in range(size))

    def lim(name):
        m = re.search(rf"\b{name}\s*;\s*/\*[^[]*\[(-?\d+), (-?\d+)\]", h)
        return int(m.group(1)), int(m.group(2))

    seq = 1
    values = {}
    for name, (off, n) in fields.items():
        lo, hi = lim(name)
        before = ram()
        old = int.from_bytes(before[off:off + n], "little", signed=lo < 0)
        new = old - 1 if old > lo else old + 1
        if name == "premise_high":
            new = max(new, values.get("premise_low", 0) + 1)
        values[name] = new
        pid = _define(h, f"LINK_ID_{name.upper()}")
        tw.uart_write(codec.encode_command("param_set", seq & 0xFF, {"id": pid, "value": new}))
        seq += 1
        tw.run(0.02)
        tw.uart_read()
        after = ram()
        want = bytearray(before)
        want[off:off + n] = new.to_bytes(n, "little", signed=lo < 0)
        if name.startswith("premise"):
            plo = int.from_bytes(want[8 * nr:8 * nr + 2], "little", signed=True)
            phi = int.from_bytes(want[8 * nr + 2:8 * nr + 4], "little", signed=True)
            want[8 * nr + 4:8 * nr + 6] = fixedpoint.premise_k(plo, phi, nr, mu_sh).to_bytes(2, "little")
        assert after == bytes(want), (name, before.hex(), after.hex(), bytes(want).hex())


def test_duty_registers_follow_the_law_output_while_running(twin):
    """write_duty (assembly): the three PDC pairs hold core_s.pdc and SEVTCMP pdc / 8 (mid on-time)
    between speed-loop samples, at several instants of a run in both directions."""
    from picdrive.firmware import core_layout, p18f4431
    tw, _ = twin
    reg = p18f4431.registers()
    b = target.build_measured(FW, Path(tempfile.mkdtemp()), name="duy2008")
    _, symbols = target.parse_map(b.hex_path.with_suffix(".map").read_text())
    core_s = next(s.address for s in symbols if s.name == "_core_s")
    pdc_at = core_layout.offsets("core_state_t", 2)["pdc"]     # the chip's (SDCC's) layout
    h = (FW / "link_fw.h").read_text()
    lt = _define(h, "LINK_ID_LINK_TIMEOUT")

    def word(lo, hi):
        return tw.peek(lo) | (tw.peek(hi) << 8)

    seen = set()
    for k, (cmd, args) in enumerate((("param_set", {"id": lt, "value": 60000}), ("set_speed", {"value": 4000}),
                                     ("start", None), ("set_speed", {"value": -4000}))):
        tw.uart_write(codec.encode_command(cmd, 0x80 + k, args))
        for _ in range(12):
            tw.run(0.0173)
            tw.uart_read()
            pdc = word(core_s + pdc_at, core_s + pdc_at + 1)
            pdcs = [word(reg[f"PDC{j}L"], reg[f"PDC{j}H"]) for j in range(3)]
            sev = word(reg["SEVTCMPL"], reg["SEVTCMPH"])
            assert pdcs == [pdc] * 3 and sev == pdc >> 3, (cmd, pdc, pdcs, sev)
            seen.add(pdc)
    assert len(seen) > 5, seen                 # the duty moved: the checks saw the law at work
