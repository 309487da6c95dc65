"""The protocol definition: tables, overrides, hash, rendering into C (gcc and avr-gcc), docs."""
import re
import shutil
import struct
import subprocess
import zlib

import pytest

from picdrive.link import protocol as P
from picdrive.firmware.p18f4431 import bits
from picdrive.link.protocol_c import render_c
from picdrive.link.protocol_doc import render_markdown
from picdrive.paths import repo_root
from picdrive.profile import load_profile

from linksupport import build


def test_static_table_ids_names_and_layout():
    t = P.build_table(2)
    names = [e.name for e in t]
    for n in ("speed_setpoint", "controller", "premise_low", "premise_high", "setpoint_weight", "u_min",
              "u_max", "current_limit", "accel_limit", "link_timeout", "stall_timeout",
              "rule1_kp", "rule1_ki", "rule1_kd", "rule1_kc", "rule2_kp", "rule2_kc",
              "speed", "setpoint", "voltage", "current", "integrator", "duty", "hall", "state", "fault",
              "mu1", "position"):
        assert n in names
    assert "rule3_kp" not in names
    assert len(P.build_table(3)) == len(t) + 4
    # ids fixed independent of r: fixed params, signals, then gains
    assert t["speed_setpoint"].id == 0 and t["speed"].id == P.SIGNAL_BASE_ID
    assert t["rule2_ki"].id == P.RULE_BASE_ID + 4 + 1
    assert [s.name for s in t.signals][:4] == list(P.DEFAULT_TELEMETRY_SIGNALS)
    assert t.signal_mask(["speed", "current"]) == 0b1001
    # persistence: everything writable but the setpoint
    assert not t["speed_setpoint"].persisted and t["controller"].persisted and t["rule1_kp"].persisted
    assert all(not s.writable and not s.persisted for s in t.signals)


def test_hash_is_crc32_of_canonical_and_covers_every_field():
    t = P.build_table(2)
    assert t.hash == zlib.crc32(t.canonical())
    base = t.hash
    variants = [
        {"rule1_kp": P.ParamOverride(scale=1 / 512)},
        {"rule1_kp": P.ParamOverride(min_raw=-100)},
        {"rule1_kp": P.ParamOverride(max_raw=100)},
        {"rule1_kp": P.ParamOverride(default_raw=5)},
        {"rule1_kp": P.ParamOverride(ctype="int32")},
        {"speed": P.ParamOverride(scale=0.5)},
    ]
    hashes = {P.build_table(2, v).hash for v in variants}
    assert base not in hashes and len(hashes) == len(variants)
    assert P.build_table(3).hash != base
    assert P.build_table(2).hash == base                   # deterministic


def test_overrides_apply_and_scale_is_float32():
    t = P.build_table(1, {"rule1_kp": P.ParamOverride(scale=0.1, min_raw=0, max_raw=30000, default_raw=1234,
                                                        ctype="int32")})
    e = t["rule1_kp"]
    assert e.ctype == "int32" and e.min_raw == 0 and e.max_raw == 30000 and e.default_raw == 1234
    assert e.scale == struct.unpack("<f", struct.pack("<f", 0.1))[0] and e.scale != 0.1
    assert e.to_raw(e.scale * 77) == 77


@pytest.mark.parametrize("ov, words", [
    ({"nope": P.ParamOverride(scale=1.0)}, "unknown entry 'nope'"),
    ({"rule3_kp": P.ParamOverride(scale=1.0)}, "unknown entry 'rule3_kp'"),
    ({"rule1_kp": P.ParamOverride(min_raw=-40000)}, "does not fit int16"),
    ({"rule1_kp": P.ParamOverride(default_raw=40000, ctype="int16")}, "does not fit int16"),
    ({"rule1_kp": P.ParamOverride(min_raw=10, max_raw=5)}, "min_raw <= default_raw <= max_raw"),
    ({"rule1_kp": P.ParamOverride(scale=0.0)}, "finite positive"),
    ({"rule1_kp": P.ParamOverride(scale=float("nan"))}, "finite positive"),
    ({"rule1_kp": P.ParamOverride(scale=1e-60)}, "float32"),
    ({"rule1_kp": P.ParamOverride(ctype="float")}, "ctype 'float'"),
    ({"speed": P.ParamOverride(ctype="int32")}, "16 bits"),
])
def test_bad_overrides_are_refused_with_a_reason(ov, words):
    with pytest.raises(P.ProtocolError, match=words):
        P.build_table(2, ov)


def test_rules_out_of_range_refused():
    for r in (0, 9, 2.0, True):
        with pytest.raises(P.ProtocolError, match="rules"):
            P.build_table(r)


def test_profile_defaults():
    prof = load_profile("duy2008")
    t = P.build_table(2, profile=prof)
    assert t["speed_setpoint"].max_raw == 2600 and t["speed_setpoint"].min_raw == -2600
    assert t["premise_high"].default_raw == 2600
    assert t["link_timeout"].default_raw == 500
    assert t["u_max"].max_value == pytest.approx(48 * prof.max_duty(), abs=t["u_max"].scale)
    assert t["current_limit"].default_value == pytest.approx(1.5, abs=t["current_limit"].scale)
    # overrides win over the profile
    t2 = P.build_table(2, {"link_timeout": P.ParamOverride(default_raw=100)}, profile=prof)
    assert t2["link_timeout"].default_raw == 100


def test_eeprom_fits_for_eight_int32_rules():
    ov = {f"rule{j}_{k}": P.ParamOverride(ctype="int32") for j in range(1, 9) for k in ("kp", "ki", "kd", "kc")}
    t = P.build_table(8, ov)
    assert t.eeprom_image_bytes <= P.EEPROM_BYTES


def test_render_c_arguments_checked():
    t = P.build_table(2)
    with pytest.raises(P.ProtocolError, match="build_id"):
        render_c(t, build_id=-1, profile_hash=0)
    with pytest.raises(P.ProtocolError, match="profile_hash"):
        render_c(t, build_id=0, profile_hash=2**32)
    with pytest.raises(P.ProtocolError, match="capture_bytes"):
        render_c(t, build_id=0, profile_hash=0, capture_bytes=33)
    with pytest.raises(P.ProtocolError, match="sample_hz"):
        render_c(t, build_id=0, profile_hash=0, sample_hz=0)


def _tables():
    yield "r2-default", P.build_table(2)
    yield "r1-int32", P.build_table(1, {"rule1_kp": P.ParamOverride(ctype="int32", min_raw=-2**31,
                                                                       max_raw=2**31 - 1),
                                        "speed": P.ParamOverride(ctype="uint16")})
    ov = {f"rule{j}_{k}": P.ParamOverride(ctype="int32") for j in range(1, 9) for k in ("kp", "ki")}
    yield "r8-mixed", P.build_table(8, ov)


@pytest.mark.parametrize("name,table", list(_tables()))
def test_rendered_c_compiles_strict_gcc_and_avr(tmp_path, name, table):
    files = render_c(table, build_id=0xCAFE0001, profile_hash=0x01020304, sample_hz=1000,
                       critical_begin="", critical_end="", sfr_bits=bits())
    assert set(files) == {"link_fw.h", "link_fw.c"}
    h = files["link_fw.h"]
    assert f"#define LINK_TABLE_HASH         0x{table.hash:08X}UL" in h
    assert "#define LINK_BUILD_ID           0xCAFE0001UL" in h
    for e in table:
        assert f"#define {e.c_id} " in h
    for k, v in files.items():
        (tmp_path / k).write_text(v)
    r = subprocess.run(["gcc", *build.STRICT, "-c", "link_fw.c", "-o", "x.o"], cwd=tmp_path,
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert shutil.which("avr-gcc"), "avr-gcc is not installed: run scripts/setup.sh (apt-get install gcc-avr)"
    r = subprocess.run([*build.AVR, "-c", "link_fw.c", "-o", "y.o"], cwd=tmp_path, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    # no heap, no floating point in the module
    nm = subprocess.run(["avr-nm", "-u", "y.o"], capture_output=True, text=True, cwd=tmp_path).stdout
    undefined = {line.split()[-1] for line in nm.splitlines() if line.strip()}
    assert "app_tx_byte" in undefined                     # the listing is what we think it is
    assert not undefined & {"malloc", "free", "calloc", "realloc", "__addsf3", "__mulsf3", "__divsf3",
                            "__floatsisf", "__fixsfsi", "__subsf3", "__cmpsf2"}, undefined
    code = re.sub(r"/\*.*?\*/", "", files["link_fw.c"] + files["link_fw.h"], flags=re.S)
    assert not re.search(r"\b(float|double|malloc|free)\b", code)


def test_docs_protocol_md_is_current():
    path = repo_root() / "docs" / "protocol.md"
    assert path.exists(), "docs/protocol.md missing: python -m picdrive.link.protocol_doc docs/protocol.md"
    assert path.read_text() == render_markdown(), \
        "docs/protocol.md is stale: regenerate with python -m picdrive.link.protocol_doc docs/protocol.md"


def test_markdown_lists_every_command_code_and_entry():
    md = render_markdown()
    for c in P.COMMANDS:
        assert f"| 0x{c.code:02X} | {c.name} |" in md
    for n in P.Nack:
        assert f"| {int(n)} | {n.name} |" in md
    for e in P.build_table(2):
        assert f"| {e.name} |" in md


@pytest.mark.skipif(shutil.which("avr-nm") is None, reason="avr-gcc/avr-nm not installed")
@pytest.mark.parametrize("rules,capture", [(2, P.CAPTURE_BYTES_DEFAULT), (5, 64)])
def test_stated_ram_budget_is_what_avr_gcc_allocates(tmp_path, rules, capture):
    t = P.build_table(rules)
    files = render_c(t, build_id=1, profile_hash=2, capture_bytes=capture, sfr_bits=bits())
    sym = build.avr_ram_bytes(build.avr_object(files, tmp_path))
    budget = P.ram_budget(t, capture)
    buffers = ("rx_buf", "rx_spill", "tx_buf", "tm_buf", "rp_data", "link_params", "cap_buf")
    assert sum(v for k, v in sym.items() if k not in buffers) == P.STATE_BYTES
    assert sym["cap_buf"] == capture and sym["link_params"] == budget["param_store"]
    assert sum(sym.values()) == sum(budget.values()) + P.STATE_BYTES
    assert re.search(rf"\*\s+total\s+{sum(budget.values()) + P.STATE_BYTES}\n", files["link_fw.h"])
