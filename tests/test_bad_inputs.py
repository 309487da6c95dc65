"""Bad inputs to every command: one line naming the problem and the fix, exit status 2, no traceback,
nothing written (the data-safety rule: docs/outputs.md).

Each case runs ``python -m picdrive ...`` in a folder of its own (so default outputs would land there),
the folder's tree is compared before and after.  The cases run concurrently in one fixture (a
subprocess each; ~1 s of start-up apiece) and are checked one test each.  Besides the corpus: the
Kt/Kb unit-slip refusal and the one constant, the design signature, and the encoder-size limit.
"""
from __future__ import annotations

import hashlib
import json
import os
import re
import subprocess
import sys
import warnings
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

from picdrive.paths import repo_root

ROOT = repo_root()
EXAMPLES = ROOT / "examples"
FIRMWARE = ROOT / "firmware_build" / "duy2008"
ENV = {**os.environ, "PYTHONPATH": os.pathsep.join(str(ROOT / d) for d in ("host", "hil")), "MPLBACKEND": "Agg"}


def _edit(text: str, **fields) -> str:
    for k, v in fields.items():
        text, n = re.subn(rf"(?m)^{k}\s*=.*$", f"{k} = {v}", text)
        assert n == 1, k
    return text


def _duy(**fields) -> str:
    return _edit((EXAMPLES / "duy2008.toml").read_text(), **fields)


# a profile whose 36 000 rpm the 48 V bridge reaches (no warning), with a 1024-line encoder
FAST = dict(resistance_ohm="0.5", viscous_friction_n_m_s="1.0e-6", torque_constant_n_m_per_a="0.01",
            back_emf_constant_v_s="0.01", speed_max_rpm="36000.0", encoder_lines="1024", name='"fast"')


def _design_dict() -> dict:
    return json.loads((EXAMPLES / "duy2008.zn.design.json").read_text())


def _files(**files):
    """setup: write files (str -> text, bytes -> bytes, dict/list -> JSON, None -> folder) into the case folder;
    in a keyword name ``__`` is a '/' and a final ``_toml``, ``_json``... the extension."""
    def setup(d: Path):
        for name, content in files.items():
            name = re.sub(r"_(toml|json|bin|md|txt|csv)$", r".\1", name.replace("__", "/"))
            p = d / name
            p.parent.mkdir(parents=True, exist_ok=True)
            if content is None:
                p.mkdir(exist_ok=True)
            elif isinstance(content, bytes):
                p.write_bytes(content)
            elif isinstance(content, str):
                p.write_text(content, encoding="utf-8")
            else:
                p.write_text(json.dumps(content))
    return setup


def _symlink(name: str, target: str):
    """setup: a folder ``target`` and a symbolic link ``name`` to it."""
    def setup(d: Path):
        (d / target).mkdir()
        os.symlink(target, d / name)
    return setup


def _fifo(name: str):
    """setup: a FIFO (named pipe) called ``name``: reading it would wait for a writer for ever."""
    return lambda d: os.mkfifo(d / name)


def _kp(value):
    d = _design_dict()
    d["law"]["rules"][0]["kp"] = value
    return d


def _resigned(**gains):
    """The ZN design with rule 1's gains edited and the signature recomputed (the file's own
    integrity check passes: only a plausibility check can refuse it)."""
    from picdrive.result import content_signature
    d = _design_dict()
    d["law"]["rules"][0].update(gains)
    d["signature"] = content_signature(d)
    return d


def _unsigned():
    d = _design_dict()
    del d["signature"]
    return d


GOOD = _duy(name='"good"')
CP1252 = GOOD.replace("# not given in the paper (assumed)", "# 4 \xb5H, not given", 1).encode("cp1252")
FOREIGN = dict(foreign__notes_txt="mine", foreign__sub__data_csv="1,2")   # a user's folder with a subfolder
DESIGN = str(EXAMPLES / "duy2008.zn.design.json")
FW = ["firmware", "--profile", "duy2008", "--design", DESIGN]
TWIN = ["twin", "--profile", "duy2008", "--firmware", str(FIRMWARE)]

# id -> (argv, setup, regex the one line must match: the field or value and the fix)
ROBUST = ["robustness", "--profile", "duy2008", "--design", str(EXAMPLES / "duy2008.fuzzy-hinf.design.json")]

CASES = {
    # --- design: the profile
    "design-missing-profile": (["design", "--profile", "nope.toml", "--method", "zn"], None,
                               r"no profile file 'nope.toml'.*give a path"),
    "design-binary-profile": (["design", "--profile", "b.toml", "--method", "zn"],
                              _files(b_toml=b"\x89PNG\r\n\x1a\n\xff\xfe\x00binary"), r"b.toml.*not UTF-8.*save it as UTF-8"),
    "design-cp1252-mu": (["design", "--profile", "c.toml", "--method", "zn"], _files(c_toml=CP1252),
                         r"c.toml: line \d+: byte 0xB5 is not UTF-8.*save it as UTF-8"),
    "design-kt-in-mNm": (["design", "--profile", "k.toml", "--method", "zn"],
                         _files(k_toml=_duy(torque_constant_n_m_per_a="14.33", back_emf_constant_v_s="0.01433")),
                         r"torque_constant.*14.33.*factor 1000.*mN m/A"),
    "design-kb-in-V-per-krpm": (["design", "--profile", "k.toml", "--method", "zn"],
                                _files(k_toml=_duy(back_emf_constant_v_s="15.0")), r"back_emf_constant.*V/krpm"),
    "design-encoder-too-fine": (["design", "--profile", "f.toml", "--method", "zn"], _files(f_toml=_duy(**FAST)),
                                r"encoder_lines = 1024 .*at most 958 lines"),
    # --- design: options
    "design-gamma-negative": (["design", "--profile", "g.toml", "--method", "fuzzy-hinf", "--gamma", "-1"],
                              _files(g_toml=GOOD), r"--gamma: '-1': expected a number > 0"),
    "design-gamma-nan": (["design", "--profile", "g.toml", "--method", "fuzzy-hinf", "--gamma", "nan"],
                         _files(g_toml=GOOD), r"--gamma: 'nan' is not a finite number"),
    "design-seed-negative": (["design", "--profile", "g.toml", "--method", "mixed-pid", "--seed", "-3"],
                             _files(g_toml=GOOD), r"--seed: '-3': expected an integer in \[0, 2147483647\]"),
    "design-option-seed-negative": (["design", "--profile", "g.toml", "--method", "mixed-pid", "--option", "seed=-3"],
                                    _files(g_toml=GOOD), r"seed -3: expected an integer in \[0, 2147483647\]"),
    "design-option-rules-text": (["design", "--profile", "g.toml", "--method", "fuzzy-hinf", "--option", "rules=abc"],
                                 _files(g_toml=GOOD), r"option rules='abc': expected an integer in \[1, 8\]"),
    "design-option-alpha-nan": (["design", "--profile", "g.toml", "--method", "fuzzy-hinf", "--option", "alpha=NaN"],
                                _files(g_toml=GOOD), r"alpha.*(finite|expected a number)"),
    "design-option-simulate-3": (["design", "--profile", "g.toml", "--method", "fuzzy-hinf", "--option", "simulate=3"],
                                 _files(g_toml=GOOD), r"option simulate=3: expected true or false"),
    "design-option-plant-model-bad": (["design", "--profile", "g.toml", "--method", "fuzzy-hinf", "--option",
                                       "plant_model=dc"], _files(g_toml=GOOD),
                                      r"option plant_model='dc': expected 'averaged' \(the default\), 'six-step'"),
    "design-profile-plant-model-bad": (["design", "--profile", "p.toml", "--method", "fuzzy-hinf"],
                                       _files(p_toml=_duy(rules='2\nplant_model = "dc"')),
                                       r"profile field 'design.plant_model' = 'dc': expected one of 'averaged', "
                                       r"'six-step'"),
    "design-option-no-equals": (["design", "--profile", "g.toml", "--method", "zn", "--option", "rules"],
                                _files(g_toml=GOOD), r"--option 'rules': expected KEY=VALUE"),
    "design-option-delay": (["design", "--profile", "g.toml", "--method", "zn", "--option", "delay_samples=7"],
                            _files(g_toml=GOOD), r"delay_samples must be 0 or 1"),
    "design-no-profile-arg": (["design", "--method", "zn"], None, r"required: --profile"),
    "design-bad-variant": (["design", "--profile", "g.toml", "--method", "fuzzy-hinf", "--variant", "vq"],
                           _files(g_toml=GOOD), r"fuzzy-hinf variant 'vq'"),
    # --- design: the output
    "design-o-user-file": (["design", "--profile", "g.toml", "--method", "zn", "-o", "mine.json"],
                           _files(g_toml=GOOD, mine_json="my notes"), r"mine.json exists and is not a file picdrive wrote"),
    "design-default-path-user-file": (["design", "--profile", "g.toml", "--method", "zn"],
                                      _files(g_toml=GOOD, **{"g.zn.design.json": "{}"}),
                                      r"g.zn.design.json exists and is not a file picdrive wrote"),
    "design-o-parent-is-file": (["design", "--profile", "g.toml", "--method", "zn", "-o", "afile/x.json"],
                                _files(g_toml=GOOD, afile="x"), r"afile is a file, not a folder"),
    "design-o-proc": (["design", "--profile", "g.toml", "--method", "zn", "-o", "/proc/picdrive-nope/"],
                      _files(g_toml=GOOD), r"cannot write in /proc"),
    # --- firmware: the design file
    "firmware-design-list": (["firmware", "--profile", "duy2008", "--design", "d.json", "-o", "fw"],
                             _files(d_json=[1, 2]), r"top level is a JSON list"),
    "firmware-design-gain-string": (["firmware", "--profile", "duy2008", "--design", "d.json", "-o", "fw"],
                                    _files(d_json=_kp("0.5")), r"rule 1 kp = \"0.5\" is not a finite number"),
    "firmware-design-hand-edited": (["firmware", "--profile", "duy2008", "--design", "d.json", "-o", "fw"],
                                    _files(d_json=_kp(-0.5)), r"changed after picdrive verified it.*re-run 'picdrive design'"),
    "firmware-design-resigned-kp-negative": (["firmware", "--profile", "duy2008", "--design", "d.json", "-o", "fw"],
                                             _files(d_json=_resigned(kp=-0.5)),
                                             r"rule 1 kp = -0.5 V/\(rad/s\) is outside the plausible range \[0, 421.7\] "
                                             r"V/\(rad/s\) on this drive \(421.7 saturates the bridge: 44.16 V from a "
                                             r"1 rpm error\) \(a negative gain is positive feedback.*edited and re-signed"),
    "firmware-design-resigned-kp-huge": (["firmware", "--profile", "duy2008", "--design", "d.json", "-o", "fw"],
                                         _files(d_json=_resigned(kp=1e6)),
                                         r"rule 1 kp = 1e\+06 V/\(rad/s\) is outside the plausible range \[0, 421.7\]"),
    "firmware-design-resigned-ki-huge": (["firmware", "--profile", "duy2008", "--design", "d.json", "-o", "fw"],
                                         _files(d_json=_resigned(ki=1e6)),
                                         r"rule 1 ki = 1e\+06 V/rad .*\[0, 4.217e\+05\].*1 rpm error in one 1 ms sample"),
    "firmware-design-unsigned": (["firmware", "--profile", "duy2008", "--design", "d.json", "-o", "fw"],
                                 _files(d_json=_unsigned()), r"has no signature.*re-run 'picdrive design'"),
    "firmware-design-not-json": (["firmware", "--profile", "duy2008", "--design", "d.json", "-o", "fw"],
                                 _files(d_json="{kp: 1"), r"d.json is not valid JSON"),
    "firmware-design-not-utf8": (["firmware", "--profile", "duy2008", "--design", "d.json", "-o", "fw"],
                                 _files(d_json=b'{"kp": "\xb5"}'), r"d.json: line 1: byte 0xB5 is not UTF-8"),
    "firmware-design-profile-string": (["firmware", "--profile", "duy2008", "--design", "d.json", "-o", "fw"],
                                       _files(d_json={**_design_dict(), "profile": "duy2008"}),
                                       r"design field 'profile' = \"duy2008\": expected a JSON object"),
    # --- firmware: the output
    "firmware-o-file": (FW + ["-o", "out.bin"], _files(out_bin="x"), r"out.bin exists and is not a folder"),
    "firmware-o-foreign-folder": (FW + ["-o", "foreign"], _files(**FOREIGN),
                                  r"foreign is not empty and was not written by picdrive"),
    "firmware-o-dot": (FW + ["-o", "."], None, r"\. is the current folder.*name a new subfolder"),
    "firmware-o-proc": (FW + ["-o", "/proc/picdrive-nope"], None,
                        r"cannot write in /proc \(it takes no new files: a virtual file system"),
    "firmware-o-symlink-to-folder": (FW + ["-o", "link"], _symlink("link", "realdir"),
                                     r"firmware folder link is a symbolic link \(to realdir\).*give the folder "
                                     r"itself or a new path"),
    "firmware-o-parent-is-file": (FW + ["-o", "afile/fw"], _files(afile="x"), r"afile is a file, not a folder"),
    "firmware-bad-hall-input": (FW + ["--hall-input", "adc"], None, r"--hall-input: invalid choice: 'adc'"),
    # --- report
    "report-o-file": (["report", "-o", "r.md"], _files(r_md="x"), r"r.md exists and is not a folder"),
    "report-o-foreign-folder": (["report", "-o", "foreign"], _files(**FOREIGN), r"foreign is not empty and was not "
                                "written by picdrive"),
    "report-o-dot": (["report", "-o", "."], None, r"current folder"),
    "report-o-proc": (["report", "-o", "/proc/picdrive-nope"], None, r"cannot write in /proc"),
    # --- demo
    "demo-missing-profile": (["demo", "--profile", "nope"], None, r"no profile file 'nope'"),
    "demo-o-file": (["demo", "-o", "d.txt"], _files(d_txt="x"), r"d.txt exists and is not a folder"),
    "demo-o-foreign-folder": (["demo", "-o", "foreign"], _files(**FOREIGN), r"not written by picdrive"),
    "demo-step-negative": (["demo", "--step-s", "-1", "-o", "dm"], None, r"--step-s/--load-s -1.0: expected seconds"),
    # --- twin
    "twin-seed-negative": (TWIN + ["--seed", "-3"], None, r"--seed: '-3': expected an integer"),
    "twin-port-range": (TWIN + ["--port", "70000"], None, r"--port: '70000': expected 0..65535"),
    "twin-speed-nan": (TWIN + ["--speed", "nan"], None, r"--speed: 'nan' is not a finite number"),
    "twin-eeprom-wrong-size": (TWIN + ["--eeprom", "ee.bin"], _files(ee_bin=b"\x00" * 10),
                               r"ee.bin: expected a 256-byte EEPROM image, found 10 bytes"),
    "twin-firmware-is-a-file": (["twin", "--profile", "duy2008", "--firmware", "fw.txt"], _files(fw_txt="int x;"),
                                r"firmware folder fw.txt is a file, not a folder: give the folder 'picdrive firmware' "
                                r"wrote"),
    "twin-eeprom-proc": (TWIN + ["--eeprom", "/proc/picdrive-nope/ee.bin"], None, r"cannot write in /proc"),
    "robustness-samples-zero": (ROBUST + ["--samples", "0", "-o", "out"], None,
                                r"--samples: '0': expected 1 \.\. 10000000 samples"),
    "robustness-output-foreign": (ROBUST + ["--samples", "2", "-o", "out"], _files(out__notes_txt="mine"),
                                  r"study folder out is not empty and was not written by picdrive"),
    "robustness-scheduler-and-workers": (ROBUST + ["--samples", "2", "-o", "out", "--workers", "2", "--scheduler",
                                                   "tcp://127.0.0.1:8786"], None, r"--workers starts a local cluster"),
    "twin-eeprom-parent-is-file": (TWIN + ["--eeprom", "afile/ee.bin"], _files(afile="x"),
                                   r"afile is a file, not a folder"),
    "twin-load-file-binary": (TWIN + ["--load-file", "l.csv"], _files(l_csv=b"\x00\xff\xfe1,2\n"),
                              r"load profile l.csv: byte 1 is not UTF-8"),
    "twin-load-file-bad-row": (TWIN + ["--load-file", "l.csv"], _files(l_csv="t_s,torque_n_m\n0,0.1\n0.5,abc\n"),
                               r"load profile l.csv: line 3 '0.5,abc' is not a row 't_s,torque_n_m'"),
    "twin-profile-not-utf8": (["twin", "--profile", "c.toml", "--firmware", str(FIRMWARE)], _files(c_toml=CP1252),
                              r"not UTF-8"),
    # --- inputs read with a type check and a size bound; a profile checked for plausibility first
    "design-profile-dev-zero": (["design", "--profile", "/dev/zero", "--method", "zn"], None,
                                r"profile /dev/zero is a character device, not a file: give the path of a profile"),
    "design-profile-fifo": (["design", "--profile", "p.toml", "--method", "zn"], _fifo("p.toml"),
                            r"profile p.toml is a FIFO \(named pipe\), not a file"),
    "design-profile-huge": (["design", "--profile", "h.toml", "--method", "zn"], _files(h_toml="#" * (2 << 20)),
                            r"profile h.toml is larger than 1024 KiB.*right file"),
    "design-profile-inertia-unit-slip": (["design", "--profile", "j.toml", "--method", "fuzzy-hinf"],
                                         _files(j_toml=_duy(inertia_kg_m2="0.03")),
                                         r"'motor.inertia_kg_m2' = 0.03 kg m\^2 is implausible.*fastest step from "
                                         r"rest to 2400 rpm takes 37.7 s \(mechanical time constant .* = 31 s\).*"
                                         r"simulate 226 s in 4.53e\+06 PWM periods \(about 159 MiB.*kg cm\^2 .*"
                                         r"J = 3e-06 kg m\^2\) or g cm\^2"),
    "firmware-design-fifo": (["firmware", "--profile", "duy2008", "--design", "d.json", "-o", "fw"], _fifo("d.json"),
                             r"design file d.json is a FIFO \(named pipe\), not a file"),
    "console-run-binary": (["console", "loop://", "--run", "b.txt"], _files(b_txt=b"\x89PNG\r\n\x1a\n\xff\x00"),
                           r"session file b.txt: line 1: byte 0x89 is not UTF-8.*binary file"),
    "console-run-dev-null": (["console", "loop://", "--run", "/dev/null"], None,
                             r"session file /dev/null is a character device, not a file"),
    "console-run-fifo": (["console", "loop://", "--run", "s.txt"], _fifo("s.txt"),
                         r"session file s.txt is a FIFO \(named pipe\), not a file"),
    # --- console: argument parsing only
    "console-unknown-option": (["console", "loop://", "--colour"], None, r"unrecognized arguments: --colour"),
}


def _tree(d: Path) -> dict:
    out = {}
    for root, dirs, files in os.walk(d):
        for n in dirs:
            out[os.path.relpath(os.path.join(root, n), d)] = "dir"
        for n in files:
            p = os.path.join(root, n)
            if not os.path.isfile(p):              # a FIFO: opening it would wait for a writer
                out[os.path.relpath(p, d)] = "special"
                continue
            out[os.path.relpath(p, d)] = hashlib.sha256(open(p, "rb").read()).hexdigest()
    return out


def _run_case(base: Path, cid: str):
    argv, setup, _ = CASES[cid]
    d = base / cid
    (d / "work").mkdir(parents=True)
    work = d / "work"
    if setup:
        setup(work)
    # '..' must point at a folder of this case alone
    before = _tree(d)
    try:
        r = subprocess.run([sys.executable, "-m", "picdrive", *argv], cwd=work, env=ENV, capture_output=True,
                           text=True, timeout=90)
    except subprocess.TimeoutExpired as e:        # a command that went on working: this case fails, not all
        r = subprocess.CompletedProcess(e.cmd, None, "", f"still running after {e.timeout} s (not refused)")
    return r, before, _tree(d)


@pytest.fixture(scope="module")
def results(request, tmp_path_factory):
    base = tmp_path_factory.mktemp("bad")
    # only the cases this run selected (-k), all of them concurrently
    chosen = [it.callspec.params["cid"] for it in request.session.items
              if it.module is request.module and "cid" in getattr(getattr(it, "callspec", None), "params", {})]
    with ThreadPoolExecutor(max_workers=4) as ex:
        futs = {cid: ex.submit(_run_case, base, cid) for cid in chosen}
        return {cid: f.result() for cid, f in futs.items()}


def test_the_corpus_is_large_and_covers_every_command():
    assert len(CASES) >= 40
    assert {a[0] for a, _, _ in CASES.values()} == {"design", "firmware", "report", "demo", "twin", "console",
                                                         "robustness"}


@pytest.mark.parametrize("cid", list(CASES))
def test_bad_input_is_refused_on_one_line_and_writes_nothing(results, cid):
    r, before, after = results[cid]
    lines = r.stderr.splitlines()
    assert "Traceback" not in r.stderr, r.stderr
    assert r.returncode == 2, (r.returncode, r.stderr[-2000:])
    assert len(lines) == 1 and lines[0].startswith("picdrive: error: "), r.stderr
    assert re.search(CASES[cid][2], lines[0]), lines[0]
    assert after == before, "the command wrote or removed something"


# ---------------------------------------------------------------------------
# Kt and Kb: one constant
# ---------------------------------------------------------------------------
@pytest.mark.parametrize("kt, kb, slip", [
    (14.33, 0.01433, "mN m/A"), (0.1433, 15.006, "V/krpm"), (0.1433, 0.0150, "V/rpm"), (1.461, 0.1433, "kg cm/A"),
    (20.29, 0.1433, "oz in/A"), (0.1433, 0.07165, "phase value"), (0.2027, 0.1433, "RMS"),
])
def test_kt_kb_ratio_outside_the_tolerance_is_refused_naming_the_unit_slip(kt, kb, slip):
    from picdrive.profile import ProfileError, loads_profile
    with pytest.raises(ProfileError, match=rf"torque_constant_n_m_per_a.*back_emf_constant_v_s.*{slip}"):
        loads_profile(_duy(torque_constant_n_m_per_a=str(kt), back_emf_constant_v_s=str(kb)))


def test_kt_kb_within_the_tolerance_is_one_constant_in_design_and_twin():
    from picdrive.profile import ProfileError, loads_profile
    from picdrive_hil.plant import plant_from_profile
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        p = loads_profile(_duy(torque_constant_n_m_per_a="0.15", back_emf_constant_v_s="0.1433"))   # 4.7 % apart
    m = p.motor
    # the design's Kt is the twin's Kt and Kb: one DC-equivalent constant
    assert m.kt_n_m_per_a == m.kb_v_s_per_rad == 0.1433
    pl = plant_from_profile(p)
    assert pl.kt_n_m_per_a == pytest.approx(m.kt_n_m_per_a, rel=1e-12)
    assert pl.kb_v_s_per_rad == pytest.approx(m.kb_v_s_per_rad, rel=1e-12)
    with pytest.raises(ProfileError, match="no common unit slip"):
        loads_profile(_duy(torque_constant_n_m_per_a="0.45", back_emf_constant_v_s="0.1433"))


# ---------------------------------------------------------------------------
# the design signature
# ---------------------------------------------------------------------------
def test_committed_designs_are_signed_and_load_as_usable(profiles):
    from picdrive.result import load_design
    files = sorted(EXAMPLES.glob("*.design.json"))
    assert len(files) == 3 * len(profiles)          # each bundled profile, each method
    for f in files:
        r = load_design(f, require_usable=True, profile=profiles[f.name.split(".")[0]])
        assert r.ok and json.loads(f.read_text())["signature"].startswith("sha256:")
        # verified means flashable: the design's firmware was built for the chip within every budget
        assert r.verification["firmware_fits_chip"]["value"] == "fits", f.name


@pytest.mark.parametrize("edit", ["kp", "status", "verification", "profile", "certificate"])
def test_a_hand_edited_design_is_not_built(tmp_path, profiles, edit):
    from picdrive.firmware import codegen
    from picdrive.result import DesignError
    d = json.loads((EXAMPLES / "duy2008.zn.design.json").read_text())
    if edit == "kp":
        d["law"]["rules"][0]["kp"] = -d["law"]["rules"][0]["kp"]
    elif edit == "status":
        d["verification"]["sim_overshoot_pct"]["ok"] = False      # a failed check, status left "verified"
    elif edit == "verification":
        d["verification"]["sim_overshoot_pct"]["value"] = 0.0
    elif edit == "profile":
        d["profile"]["sha256"] = profiles["duy2008"].sha256[:-1] + "0"
    else:
        d["certificate"]["edited"] = True
    p = tmp_path / "d.design.json"
    p.write_text(json.dumps(d, indent=1))
    with pytest.raises(DesignError, match="changed after picdrive verified it.*re-run 'picdrive design'"):
        codegen.generate(profiles["duy2008"], p)
    # re-ordering and re-indenting the file is not an edit
    p.write_text(json.dumps(json.loads((EXAMPLES / "duy2008.zn.design.json").read_text())))
    assert codegen.generate(profiles["duy2008"], p).files["drive_params.h"]


# ---------------------------------------------------------------------------
# the encoder's M/T arithmetic
# ---------------------------------------------------------------------------
def _fast(lines: int):
    from picdrive.profile import loads_profile
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        return loads_profile(_duy(**{**FAST, "encoder_lines": str(lines)}))


def test_a_fine_encoder_on_a_fast_motor_is_refused_with_the_limit_not_as_a_bug(tmp_path):
    from picdrive.firmware import codegen, fixedpoint
    from picdrive.control_law import Rule, ScheduledLaw
    from picdrive.result import DesignResult, save_design
    p = _fast(1024)
    with pytest.raises(fixedpoint.FixedPointError, match=r"encoder_lines = 1024 .*CORE_MT_DMAX = 69997.*at most 958 "
                                                          r"lines.*down to 31290 rpm"):
        fixedpoint.check_profile_arithmetic(p)
    law = ScheduledLaw(rules=(Rule(0.01, 0.1),), premise_rad_s=(0.0, 1.0), sample_time_s=1e-3, u_min_v=-44.0,
                       u_max_v=44.0)
    d = save_design(DesignResult(method="zn", status="verified", profile_name=p.name, profile_sha256=p.sha256,
                                 law=law), tmp_path / "d.design.json")
    with pytest.raises(fixedpoint.FixedPointError, match="at most 958 lines"):
        codegen.generate(p, d)
    # the limit it names is the limit: 958 lines builds (gcc -Werror), 959 does not plan
    with pytest.raises(fixedpoint.FixedPointError, match="at most 958 lines"):
        fixedpoint.check_profile_arithmetic(_fast(959))
    p958 = _fast(958)
    fixedpoint.check_profile_arithmetic(p958)
    d = save_design(DesignResult(method="zn", status="verified", profile_name=p958.name, profile_sha256=p958.sha256,
                                 law=law), tmp_path / "d958.design.json")
    fw = codegen.generate(p958, d)
    dmax = int(re.search(r"CORE_MT_DMAX\s+UINT32_C\((\d+)\)", fw.files["drive_params.h"]).group(1))
    assert dmax <= 65534
    codegen.write_firmware(fw, tmp_path / "fw958", check=True)


def test_the_design_command_refuses_the_encoder_before_designing(tmp_path):
    from picdrive.gate import run_design
    from picdrive.firmware.fixedpoint import FixedPointError
    with pytest.raises(FixedPointError, match="at most 958 lines"):
        run_design(_fast(1024), "zn", progress=False)
