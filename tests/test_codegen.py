"""`picdrive firmware`: output, determinism, the committed example, names from
p18f4431.inc, strict compiles (gcc and 16-bit-int avr-gcc), and refusals that
leave no output behind."""
import hashlib
import json
import re
import shutil
from pathlib import Path

import pytest

from picdrive import cli
from picdrive.firmware import codegen, p18f4431
from picdrive.outputs import MARKER
from picdrive.control_law import Rule, ScheduledLaw
from picdrive.paths import firmware_build_dir, repo_root
from picdrive.profile import load_profile
from picdrive.result import DesignResult, save_design

RPM = 3.141592653589793 / 30
EXAMPLE_DESIGN = repo_root() / "examples" / "duy2008.fuzzy-hinf.design.json"
COMMITTED = firmware_build_dir() / "duy2008"


def run_cli(monkeypatch, *args) -> int:
    # only this piece's command: the CLI's error handling without the other commands' imports
    monkeypatch.setattr(cli, "COMMAND_MODULES", ["picdrive.firmware.codegen"])
    # the C generation only: the PIC18 HEX build and its budgets are tests/test_target.py's
    return cli.main(["firmware", "--no-hex", *map(str, args)])


def fixture_design(tmp_path, profile, name="fixture", law=None, **kw) -> Path:
    law = law or ScheduledLaw(rules=(Rule(0.2, 5.0, 0.0, 10.0), Rule(0.15, 4.0, 0.0, 8.0)),
                              premise_rad_s=(0.0, 2600 * RPM), sample_time_s=1e-3, u_min_v=-44.16, u_max_v=44.16)
    base = dict(method="zn", status="verified", profile_name=profile.name, profile_sha256=profile.sha256,
                law=law, variant="test-fixture")
    base.update(kw)
    return save_design(DesignResult(**base), tmp_path / f"{name}.design.json")


def profile_file(tmp_path, name, **changes) -> Path:
    text = (repo_root() / "examples" / "duy2008.toml").read_text()
    for key, value in changes.items():
        import re
        text, n = re.subn(rf"(?m)^{key}\s*=.*$", f"{key} = {value}", text)
        assert n == 1, key
    p = tmp_path / f"{name}.toml"
    p.write_text(text)
    return p


def test_cli_writes_the_folder_and_prints_what_it_chose(tmp_path, monkeypatch, capsys):
    prof = load_profile("duy2008")
    design = fixture_design(tmp_path, prof)
    out = tmp_path / "fw"
    assert run_cli(monkeypatch, "--profile", "duy2008", "--design", design, "-o", out) == 0
    text = capsys.readouterr().out
    for what in ("taper_start    52.8 V", "taper_end      57.6 V", "trip           60.0 V", "0.80 x switch 100 V",
                 "PTPER = 499", "20000.0 Hz", "DTCON = 0x14", "1000 ns", "max duty", "0.9200", "pin map",
                 "RC3", "Q formats", "error", "build id", "encoder M/T"):
        assert what in text, what
    for f in ("drive.c", "drive_core.c", "drive_params.h", "link_fw.c", "link_fw.h", "main_xc8.c",
              "config_xc8.c", "Makefile", "host/xc.h", "board.json", "README.md"):
        assert (out / f).is_file(), f
    board = json.loads((out / "board.json").read_text())
    assert [p["name"] for p in board["hall_pins"]] == ["RC3", "RC4", "RC5"] and board["flta_pin"]["name"] == "RC1"
    hb = codegen.host_build(out)
    assert [Path(s).name for s in hb["sources"]] == list(codegen.HOST_SOURCES)
    assert hb["include_dirs"][0].endswith("host")
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".fw.")]     # no temp folder left


def test_a_bus_without_a_regeneration_window_is_refused(tmp_path, monkeypatch, capsys):
    prof_path = profile_file(tmp_path, "tight", bus_voltage_v="80")          # 80 V on 100 V switches
    design = fixture_design(tmp_path, load_profile(prof_path))
    out = tmp_path / "fw"
    assert run_cli(monkeypatch, "--profile", prof_path, "--design", design, "-o", out) == 2
    err = capsys.readouterr().err
    assert "leave no regeneration window" in err and "switches rated at least 105 V" in err
    assert "Traceback" not in err and not out.exists()


def test_generation_is_deterministic(tmp_path):
    prof = load_profile("duy2008")
    design = fixture_design(tmp_path, prof)
    a = codegen.generate(prof, design)
    b = codegen.generate(load_profile("duy2008"), design)
    assert a.files == b.files and a.build_id == b.build_id
    for name, text in a.files.items():                 # nothing that changes with the clock
        assert not re.search(r"\b20\d\d-\d\d-\d\d|\b\d\d:\d\d:\d\d\b", text), name
    # the build id changes with the inputs
    c = codegen.generate(prof, design, fault_pin="RD4")
    assert c.build_id != a.build_id


def test_committed_example_regenerates_to_the_same_bytes(tmp_path):
    prof = load_profile("duy2008")
    assert COMMITTED.is_dir(), "firmware_build/duy2008 is not committed"
    fw = codegen.generate(prof, EXAMPLE_DESIGN)
    # the HEX is compared with a fresh PIC18 build in tests/test_target.py
    on_disk = {str(p.relative_to(COMMITTED)): p.read_text() for p in COMMITTED.rglob("*")
               if p.is_file() and "build" not in p.relative_to(COMMITTED).parts and p.suffix != ".hex"}
    assert set(on_disk) == set(fw.files), set(on_disk) ^ set(fw.files)
    # the marker on disk lists the HEX as well (written with it); the rest of it is what generate() writes
    marker = json.loads(on_disk.pop(MARKER))
    hex_digest = marker["files"].pop("duy2008.hex")
    assert hex_digest == hashlib.sha256((COMMITTED / "duy2008.hex").read_bytes()).hexdigest()
    assert marker == json.loads(fw.files[MARKER])
    for name, text in fw.files.items():
        if name == MARKER:
            continue
        assert on_disk[name] == text, (f"firmware_build/duy2008/{name} differs from what picdrive firmware "
                                       "generates now: regenerate it (bench/firmware.py --regenerate)")


def test_every_sfr_and_bit_name_exists_in_the_inc():
    sources = [p.read_text() for p in sorted(COMMITTED.glob("*.[ch]"))]
    sfrs, bit_uses, unknown = p18f4431.names_used(sources)
    regs, bits = p18f4431.registers(), p18f4431.bits()
    assert len(sfrs) > 40 and len(bit_uses) > 20
    assert sfrs <= set(regs)
    assert not [(r, b) for r, b in bit_uses if r not in bits or b not in bits[r]]
    assert unknown == set(), f"upper-case names neither in p18f4431.inc nor defined in the sources: {unknown}"
    # config pragmas use the .inc's CONFIG names and values
    cfg = p18f4431.config_settings()
    import re
    for k, v in re.findall(r"#pragma config (\w+) = (\w+)", (COMMITTED / "config_xc8.c").read_text()):
        assert k in cfg and v in cfg[k], (k, v)


def test_strict_compiles_gcc_and_16bit_avr_gcc():
    done = codegen.build_check(COMMITTED)
    assert done[0] == "gcc"
    if shutil.which("avr-gcc"):
        assert "avr-gcc" in done


# ---------------------------------------------------------------------------
# refusals: a clear error, exit status 2, no output folder, an old folder untouched
# ---------------------------------------------------------------------------
def _refused(monkeypatch, capsys, tmp_path, profile, design, match, extra=()):
    out = tmp_path / "out"
    code = run_cli(monkeypatch, "--profile", profile, "--design", design, "-o", out, *extra)
    err = capsys.readouterr().err
    assert code == 2 and err.startswith("picdrive: error: ") and len(err.strip().splitlines()) == 1, err
    import re
    assert re.search(match, err), err
    assert not out.exists()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".out.")]


def test_refuses_a_failed_design(tmp_path, monkeypatch, capsys):
    prof = load_profile("duy2008")
    d = fixture_design(tmp_path, prof, status="failed", reasons=["closed loop unstable at vertex 2"])
    _refused(monkeypatch, capsys, tmp_path, "duy2008", d, r"failed its verification.*vertex 2")


def test_refuses_a_design_without_a_law(tmp_path, monkeypatch, capsys):
    prof = load_profile("duy2008")
    d = DesignResult(method="fuzzy-hinf", status="verified", profile_name=prof.name, profile_sha256=prof.sha256,
                     law=None, variant="paper")
    p = save_design(d, tmp_path / "paper.design.json")
    _refused(monkeypatch, capsys, tmp_path, "duy2008", p, r"no law the six-step firmware can run")


def test_refuses_a_design_of_another_profile(tmp_path, monkeypatch, capsys):
    other = load_profile("assawinchaichote2016")
    d = fixture_design(tmp_path, other)
    _refused(monkeypatch, capsys, tmp_path, "duy2008", d, r"re-run 'picdrive design' on this profile")


def test_refuses_an_impossible_pin_map(tmp_path, monkeypatch, capsys):
    d = fixture_design(tmp_path, load_profile("duy2008"))
    _refused(monkeypatch, capsys, tmp_path, "duy2008", d, r"IC1..IC3 and the QEI share.*INT0..INT2",
             extra=("--hall-input", "ic"))


def test_refuses_an_impossible_pwm_dead_time_combination(tmp_path, monkeypatch, capsys):
    # the profile accepts it (2 x 2001 + 988 ns < half of 10 us) but DTCON rounds 2001 ns up to
    # 2050 ns, which leaves less than half of the period for the duty
    pf = profile_file(tmp_path, "tight", pwm_frequency_hz="100000.0", dead_time_ns="2001.0",
                      bootstrap_refresh_ns="988.0")
    prof = load_profile(pf)
    d = fixture_design(tmp_path, prof)
    _refused(monkeypatch, capsys, tmp_path, pf, d, r"less than half.*lower inverter.pwm_frequency_hz")


def test_refuses_coefficients_that_cannot_be_represented(tmp_path, monkeypatch, capsys):
    prof = load_profile("duy2008")
    law = ScheduledLaw(rules=(Rule(100.0, 5.0), Rule(1e-4, 5.0)), premise_rad_s=(0.0, 272.0),
                       sample_time_s=1e-3, u_min_v=-44.0, u_max_v=44.0)
    d = fixture_design(tmp_path, prof, law=law)
    _refused(monkeypatch, capsys, tmp_path, "duy2008", d, r"rule 2 kp = 0.0001 .*cannot be represented")


def test_an_existing_folder_survives_a_refusal_and_a_failed_build_check(tmp_path, monkeypatch, capsys):
    prof = load_profile("duy2008")
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("old")
    bad = fixture_design(tmp_path, prof, name="bad", status="failed", reasons=["x"])
    good = fixture_design(tmp_path, prof)
    assert run_cli(monkeypatch, "--profile", "duy2008", "--design", bad, "-o", out) == 2
    assert (out / "keep.txt").read_text() == "old"
    # a folder picdrive did not write is never replaced (docs/outputs.md)
    assert run_cli(monkeypatch, "--profile", "duy2008", "--design", good, "-o", out) == 2
    assert "not written by picdrive" in capsys.readouterr().err and (out / "keep.txt").read_text() == "old"
    assert sorted(p.name for p in out.iterdir()) == ["keep.txt"]

    # a firmware folder picdrive wrote is replaced whole, or left as it was when the build check fails
    own = tmp_path / "own"
    assert run_cli(monkeypatch, "--profile", "duy2008", "--design", good, "-o", own) == 0
    assert (own / "drive.c").is_file() and (own / ".picdrive-output").is_file()
    before = {p.name: p.read_bytes() for p in own.iterdir() if p.is_file()}

    def broken(folder):
        raise codegen.CodegenError("does not compile (simulated)")
    monkeypatch.setattr(codegen, "build_check", broken)
    capsys.readouterr()
    assert run_cli(monkeypatch, "--profile", "duy2008", "--design", good, "-o", own) == 2
    assert "does not compile" in capsys.readouterr().err
    assert {p.name: p.read_bytes() for p in own.iterdir() if p.is_file()} == before
    assert not [p for p in tmp_path.iterdir() if p.name.startswith((".out.", ".own."))]
    monkeypatch.undo()
    assert run_cli(monkeypatch, "--profile", "duy2008", "--design", good, "-o", own) == 0
    # ... as long as its files are picdrive's: one edited by hand stops it
    (own / "drive.c").write_text("edited by hand")
    capsys.readouterr()
    assert run_cli(monkeypatch, "--profile", "duy2008", "--design", good, "-o", own) == 2
    assert "drive.c (changed since picdrive wrote it)" in capsys.readouterr().err
    assert (own / "drive.c").read_text() == "edited by hand"


def test_host_build_of_a_non_firmware_folder(tmp_path):
    with pytest.raises(codegen.CodegenError, match="not a generated firmware folder"):
        codegen.host_build(tmp_path)


def test_uart_and_bus_sense_plans():
    n, baud = codegen.uart_brg(115200)
    assert n == 86 and abs(baud - 115200) / 115200 < 0.003
    assert codegen.uart_brg(1_000_000) == (9, 1_000_000.0)
    with pytest.raises(codegen.CodegenError, match="more than 2 %"):
        codegen.uart_brg(700_000)
    b = codegen.bus_sense(load_profile("duy2008"))
    assert b["uv"] < 512 < b["ov"] <= 1023


@pytest.mark.parametrize("variant", ["ic-halls-no-encoder", "sixty-degree-halls-rd4", "loop-100hz", "loop-20khz"])
def test_variants_generate_and_compile(tmp_path, variant):
    changes, opts = {}, {}
    if variant == "ic-halls-no-encoder":
        changes = {"encoder_lines": "0", "speed_source": '"hall"'}
        opts = {"hall_input": "ic"}
    elif variant == "sixty-degree-halls-rd4":
        changes = {"hall_spacing_deg": "60", "hall_offset_deg": "30.0"}
        opts = {"fault_pin": "RD4"}
    elif variant == "loop-100hz":
        changes = {"speed_loop_hz": "100.0"}
    else:
        changes = {"speed_loop_hz": "20000.0"}
    prof = load_profile(profile_file(tmp_path, variant, **changes))
    ts = 1.0 / prof.control.speed_loop_hz
    law = ScheduledLaw(rules=(Rule(0.2, 5.0, 0.0, 10.0), Rule(0.15, 4.0, 0.0, 8.0)),
                       premise_rad_s=(0.0, 2600 * RPM), sample_time_s=ts, u_min_v=-44.16, u_max_v=44.16)
    d = fixture_design(tmp_path, prof, law=law)
    fw = codegen.generate(prof, d, **opts)
    out = codegen.write_firmware(fw, tmp_path / "out")        # includes the gcc / avr-gcc build check
    params = (out / "drive_params.h").read_text()
    if variant == "ic-halls-no-encoder":
        assert "#define FW_HALL_IC 1" in params and "#define FW_SPEED_ENCODER 0" in params
        assert "#define FW_HALL_PORT PORTA" in params
    elif variant == "sixty-degree-halls-rd4":
        assert "#pragma config FLTAMX = RD4" in (out / "config_xc8.c").read_text()
        assert "#define FW_HALL_VALID_MASK 0xDBu" in params      # 010 and 101 invalid
    elif variant == "loop-100hz":
        assert fw.plan.loop_hz == 100.0 and fw.plan.loop_div * fw.plan.tcy_per_tick == 100000
    else:
        assert fw.plan.loop_hz == 20000.0 and fw.plan.tcy_per_tick == 500
    # the hardware watchdog: at least 32 ms and 4 speed-loop periods (it is cleared after a sample)
    wdps = {"loop-100hz": 16}.get(variant, 8)
    assert f"#pragma config WDPS = {wdps} " in (out / "config_xc8.c").read_text()
    assert f"#pragma config WDPS={wdps} " in (out / "main_sdcc.c").read_text()
    assert f"#define FW_WDT_MS {4 * wdps}u" in params
    sfrs, bit_uses, unknown = p18f4431.names_used([p.read_text() for p in out.glob("*.[ch]")])
    assert unknown == set() and sfrs <= set(p18f4431.registers())


def test_the_speed_loop_budget_is_a_share_of_the_loop_period_the_firmware_runs(tmp_path):
    """40 % of the speed loop's own period (drive_params.h: FW_LOOP_DIV Timer2 interrupts of
    FW_TCY_PER_TICK_MS ms + FW_TCY_PER_TICK_MOD Tcy): 4,000 cycles at 1 kHz, 2,000 at 2 kHz, 8,000
    every second 1 ms interrupt (a fixed 4,000 let a 2 kHz loop take 80 % of the chip)."""
    from picdrive.firmware.codegen import folder_budgets
    from picdrive.paths import firmware_build_dir
    src = (firmware_build_dir() / "duy2008" / "drive_params.h").read_text()
    for n in ("FW_LOOP_DIV 1u", "FW_TCY_PER_TICK_MS 1u", "FW_TCY_PER_TICK_MOD 0u"):
        assert f"#define {n}" in src
    cases = {4000: src,
             2000: src.replace("FW_TCY_PER_TICK_MS 1u", "FW_TCY_PER_TICK_MS 0u")
                      .replace("FW_TCY_PER_TICK_MOD 0u", "FW_TCY_PER_TICK_MOD 5000u"),
             8000: src.replace("FW_LOOP_DIV 1u", "FW_LOOP_DIV 2u")}
    for cycles, text in cases.items():
        d = tmp_path / str(cycles)
        d.mkdir()
        (d / "drive_params.h").write_text(text)
        assert folder_budgets(d).speed_loop_cycles == cycles


def test_watchdog_period_covers_four_speed_loop_periods_and_32_ms():
    """The hardware watchdog is cleared after a speed-loop sample: its period must cover several
    of them (a 10 Hz loop, the profile's slowest, would otherwise reset a healthy chip)."""
    assert [codegen.wdt_postscale(hz) for hz in (20000.0, 1000.0, 125.0, 100.0, 10.0)] == [8, 8, 8, 16, 128]
    for hz in (10.0, 33.0, 100.0, 1000.0, 20000.0):
        ms = 4 * codegen.wdt_postscale(hz)
        assert ms >= 32 and ms >= 4 * 1000.0 / hz and (ms == 32 or ms / 2 < 4 * 1000.0 / hz)
