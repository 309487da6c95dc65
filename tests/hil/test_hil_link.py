"""Handshake and parameters through the link: the board is the one the profile
says, its table round-trips values, and out-of-range or read-only writes are
NACKed without changing anything."""
import pytest

from picdrive.link import protocol as P
from picdrive.link.client import NackError


def test_handshake_identifies_the_profile_and_table(open_bench):
    b = open_bench("duy2008")
    info = b.link.info
    assert info.proto_version[0] == P.PROTOCOL_VERSION[0]
    assert info.profile_hash == int(b.profile.sha256[:8], 16)
    assert info.table_hash == b.link.table.hash
    assert info.sample_hz == pytest.approx(b.profile.control.speed_loop_hz)
    st = b.link.status()
    assert st.state == P.State.IDLE and st.fault == P.Fault.NONE


def test_parameter_round_trip(open_bench):
    b = open_bench("duy2008")
    lk = b.link
    for name in ("rule1_kp", "link_timeout", "current_limit", "u_max"):
        e = lk.param(name)
        assert e.writable
        old = lk.get_raw(name)[name]
        new = old - 1 if old > e.min_raw else old + 1
        assert lk.set_raw(name, new) == new
        assert lk.get_raw(name)[name] == new
        # engineering units: what comes back is the value rounded to the board's resolution
        got = lk.set(name, new * e.scale)
        assert got == pytest.approx(new * e.scale)
        lk.set_raw(name, old)
        assert lk.get_raw(name)[name] == old


def test_out_of_range_and_read_only_writes_are_nacked_and_change_nothing(open_bench):
    b = open_bench("duy2008")
    lk = b.link
    names = [e.name for e in lk.params() if e.writable and not e.values]
    before = lk.get_raw(*names)
    for name in ("current_limit", "link_timeout", "rule1_kp"):
        e = lk.param(name)
        for raw in (e.max_raw + 1, e.min_raw - 1):
            if not -32768 <= raw <= 65535:
                continue
            with pytest.raises(NackError) as ei:
                lk.set_raw(name, raw, check=False)
            assert ei.value.code == P.Nack.OUT_OF_RANGE
    speed = lk.param("speed")
    assert not speed.writable
    with pytest.raises(NackError) as ei:
        lk.set_raw("speed", 0, check=False)
    assert ei.value.code == P.Nack.READ_ONLY
    assert lk.get_raw(*names) == before
    st = lk.status()
    assert st.state == P.State.IDLE and st.fault == P.Fault.NONE
