"""The DC bus in both twins: a rotor driven above the bus speed by an overhauling load pumps the
bus capacitor up through the body diodes (the supply cannot take the current back), the firmware
reads it on AN1 and latches OVERVOLTAGE at its trip level, on the software twin (the generated C)
and the processor twin (the bundled HEX on the PIC18 core), in simulated time.  The bus voltage is also a
telemetry signal: the firmware reports AN1, scaled from the profile's divider, over the link."""
from __future__ import annotations

import numpy as np
import pytest

from picdrive.firmware import codegen, target
from picdrive.link import codec
from picdrive.link import protocol as P
from picdrive.paths import firmware_build_dir
from picdrive.profile import bus_guard, load_profile
from picdrive_hil.twin import Twin
from support.twin_uart import command

FW = firmware_build_dir() / "duy2008"


@pytest.fixture(scope="module")
def build(tmp_path_factory):
    return target.build_measured(FW, tmp_path_factory.mktemp("bus-hex"))


@pytest.mark.parametrize("kind", ["sil", "pil"])
def test_an_overhauling_load_pumps_the_bus_up_and_the_firmware_trips_on_it(kind, build):
    prof = load_profile("duy2008")
    ov_v = codegen.bus_sense(prof)["ov_v"]
    kw = dict(hex_file=build.hex_path, enlarged_memory=not build.on_chip) if kind == "pil" else {}
    tw = Twin("duy2008", FW, seed=0, load_mode="active", **kw)
    tw.run(0.01)
    assert tw.state()["bus_voltage_v"] == pytest.approx(prof.inverter.bus_voltage_v)
    # idle, outputs off; the load drives the rotor forward (a lowered weight, a vehicle downhill)
    tw.set_load_torque(-0.1)
    t_cross, t_trip, v_trip = None, None, None
    for k in range(2000):
        tw.run(0.002)
        v = tw.state()["bus_voltage_v"]
        if t_cross is None and v > ov_v:
            t_cross = tw.t
        st = command(tw, "status", k % 256)
        if st["fault"] == P.Fault.OVERVOLTAGE:
            t_trip, v_trip = tw.t, v
            break
    print(f"{kind}: bus above the {ov_v:.1f} V trip level at {t_cross} s, OVERVOLTAGE latched at {t_trip} s "
          f"(bus {v_trip} V)")
    assert t_cross is not None and t_trip is not None
    # the speed loop samples AN1 every 1 ms and debounces 10 samples; the status is polled every 2 ms
    assert t_cross <= t_trip <= t_cross + 0.010 + 0.004
    assert not tw.state()["outputs_active"]


SIGNALS = [d.name for d in P.SIGNALS]


def test_the_signal_table_holds_the_bus_voltage_within_its_limits():
    assert "bus_voltage" in SIGNALS and len(SIGNALS) <= 16
    # the largest telemetry frame the host may ask for still fits the payload
    assert codec.telemetry_payload_len(len(P.DEFAULT_TELEMETRY_SIGNALS), P.DEFAULT_SAMPLES_PER_FRAME) <= P.MAX_PAYLOAD
    assert codec.telemetry_payload_len(len(P.DEFAULT_TELEMETRY_SIGNALS) + 1, 3) <= P.MAX_PAYLOAD


def _entry(tw, name):
    """The board's own description of entry ``name`` (param_info over the link)."""
    for k in range(64):
        e = codec.decode_param_info(codec.reply_payload("param_info", command(tw, "param_info", k, {"index": k})))
        if e.name == name:
            return e
    raise AssertionError(f"{name} not in the board's table")


@pytest.mark.parametrize("kind", ["sil", "pil"])
def test_the_twin_reports_the_bus_rising_under_an_overhauling_load(kind, request):
    prof = load_profile("duy2008")
    g = bus_guard(prof.inverter)
    kw = {}
    if kind == "pil":
        b = request.getfixturevalue("build")
        kw = dict(hex_file=b.hex_path, enlarged_memory=not b.on_chip)
    tw = Twin("duy2008", FW, seed=0, load_mode="active", **kw)
    tw.run(0.01)
    e = _entry(tw, "bus_voltage")
    assert e.signal and e.unit == "V" and not e.writable
    assert e.scale == pytest.approx(1.0 / g.counts_per_v, rel=1e-6)      # the profile's AN1 divider
    (v0,) = command(tw, "param_get", 1, {"ids": [e.id]})["values"]
    assert v0 * e.scale == pytest.approx(prof.inverter.bus_voltage_v, abs=2 * e.scale)
    idx = SIGNALS.index("bus_voltage")
    cfg = command(tw, "telem_config", 2, {"mask": 1 << idx, "decimation": 1, "samples_per_frame": 4})
    assert cfg["payload_len"] == codec.telemetry_payload_len(1, 4)
    tw.set_load_torque(-0.1)                 # the load drives the rotor forward, outputs off
    dec, got, truth = codec.StreamDecoder(), [], []
    for _ in range(400):
        tw.run(0.001)
        truth.append((tw.t, tw.state()["bus_voltage_v"]))
        for f in dec.feed(tw.uart_read()):
            if f.type == P.MSG_TELEMETRY:
                _, vals = codec.decode_telemetry(f.payload, 1)
                got.append((tw.t, vals[-1, 0] * e.scale))
    got, truth = np.array(got), np.array(truth)
    print(f"{kind}: bus over the link: {got[0, 1]:.2f} V .. {got[:, 1].max():.2f} V in {len(got)} frames; "
          f"true {truth[0, 1]:.2f} .. {truth[:, 1].max():.2f} V")
    assert len(got) > 50
    assert got[:, 1].max() > prof.inverter.bus_voltage_v + 3.0          # the pumping is seen
    # each frame's newest sample is the bus as the plant had it up to 10 ms earlier (frame fill,
    # the transmit queue, UART time, the 1 ms polling here), within the ADC's resolution; at full
    # scale (1023 counts, twice the nominal bus with the assumed divider) the reading clips
    full = e.max_raw * e.scale
    assert got[:, 1].max() <= full
    for t, v in got[got[:, 1] < full - e.scale]:
        w = truth[(truth[:, 0] <= t + 1e-9) & (truth[:, 0] >= t - 0.010), 1]
        assert w.min() - 2 * e.scale <= v <= w.max() + 2 * e.scale, (t, v, w)
