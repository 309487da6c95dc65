"""The DC bus in both twins: a rotor driven above the bus speed by an overhauling load pumps the
bus capacitor up through the body diodes (the supply cannot take the current back), the firmware
reads it on AN1 and latches OVERVOLTAGE at its trip level, on the software twin (the generated C)
and the processor twin (the bundled HEX on the PIC18 core), in simulated time."""
from __future__ import annotations

import pytest

from picdrive.firmware import codegen, target
from picdrive.link import protocol as P
from picdrive.paths import firmware_build_dir
from picdrive.profile import load_profile
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
