"""Pin map: valid maps for the profiles, clear refusals of impossible ones."""
import pytest

from picdrive.firmware import pinmap
from picdrive.profile import load_profile


def test_duy2008_halls_on_int_with_encoder():
    pm = pinmap.choose_pinmap(load_profile("duy2008"))
    assert pm.hall_input == "int" and pm.encoder
    assert [pm.assign[h][0] for h in ("hall_a", "hall_b", "hall_c")] == ["RC3", "RC4", "RC5"]
    assert pm.assign["encoder_a"] == ("RA3", "QEA") and pm.assign["fault_flta"] == ("RC1", "FLTA")
    assert pm.hall_port == "PORTC" and pm.hall_shift == 3
    t = pm.tris()
    assert t["B"] == 0xC0 and t["A"] == 0xFF and t["C"] == 0xFF
    pins = [p for p, _ in pm.assign.values()]
    assert len(pins) == len(set(pins))


def test_hall_on_ic_with_encoder_is_refused_naming_the_conflict_and_fix():
    with pytest.raises(pinmap.PinMapError, match=r"share pins RA2..RA4.*INT0..INT2.*encoder_lines = 0"):
        pinmap.choose_pinmap(load_profile("duy2008"), hall_input="ic")


def test_hall_on_ic_without_encoder():
    prof = load_profile("duy2008").replace(sensors={"encoder_lines": 0, "speed_source": "hall"})
    pm = pinmap.choose_pinmap(prof, hall_input="ic", fault_pin="RD4")
    assert pm.assign["hall_a"] == ("RA2", "CAP1") and pm.hall_port == "PORTA" and pm.hall_shift == 2
    assert pm.config["FLTAMX"] == "RD4" and "encoder_a" not in pm.assign


def test_check_catches_each_conflict():
    pm = pinmap.choose_pinmap(load_profile("duy2008"))
    def with_(assign=None, config=None):
        return pinmap.PinMap(pm.hall_input, pm.encoder, {**pm.assign, **(assign or {})},
                             {**pm.config, **(config or {})})
    with pytest.raises(pinmap.PinMapError, match="assigned twice"):
        pinmap.check_pinmap(with_({"bus_current": ("RC3", "INT0")}))
    with pytest.raises(pinmap.PinMapError, match="cannot carry"):
        pinmap.check_pinmap(with_({"hall_a": ("RB4", "INT0")}))
    with pytest.raises(pinmap.PinMapError, match="PGC"):
        pinmap.check_pinmap(with_({"hall_c": ("RB6", "KBI2")}))
    with pytest.raises(pinmap.PinMapError, match="FLTAMX = RD4"):
        pinmap.check_pinmap(with_({"fault_flta": ("RD4", "FLTA")}))
    with pytest.raises(pinmap.PinMapError, match="LVP = OFF"):
        pinmap.check_pinmap(with_(config={"LVP": "ON"}))
    with pytest.raises(pinmap.PinMapError, match="SSPMX = RD1"):
        pinmap.check_pinmap(with_(config={"SSPMX": "RC7"}))
    with pytest.raises(pinmap.PinMapError, match="RC1 or RD4"):
        pinmap.choose_pinmap(load_profile("duy2008"), fault_pin="RC2")
