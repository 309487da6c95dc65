"""The gate of `picdrive design`: a design that fails its verification is written only to
``<stem>.<method>.design.failed.json`` for inspection, the command exits 1, and a good design file
already at the destination is left byte for byte as it was."""
import json
import shutil
import subprocess
import sys

from picdrive.paths import repo_root

EXAMPLES = repo_root() / "examples"


def _design(cwd, *args):
    return subprocess.run([sys.executable, "-m", "picdrive", "design", *args, "--no-progress"], cwd=cwd,
                          capture_output=True, text=True, timeout=300)


def _setup(tmp_path):
    """The 2016 profile with its committed zn design next to it (the good file)."""
    prof = tmp_path / "assawinchaichote2016.toml"
    shutil.copy(EXAMPLES / "assawinchaichote2016.toml", prof)
    good = tmp_path / "assawinchaichote2016.zn.design.json"
    shutil.copy(EXAMPLES / "assawinchaichote2016.zn.design.json", good)
    return prof, good, good.read_bytes()


def _check_failed(r, failed, good, before):
    assert r.returncode == 1, r.stdout + r.stderr
    last = r.stdout.rstrip().splitlines()[-1]
    assert last.startswith("design FAILED its verification; wrote it for inspection only to ") and \
        last.endswith(failed.name), r.stdout
    d = json.loads(failed.read_text())
    assert d["status"] == "failed" and d["reasons"] and d["variant"] == "paper2016"
    assert any("unstable" in why for why in d["reasons"])        # the paper's kd at 1 kHz
    assert good.read_bytes() == before                         # the good design is untouched


def test_a_failed_design_goes_next_to_the_profile_as_failed_json(tmp_path):
    prof, good, before = _setup(tmp_path)
    # the 2016 paper's ZN gains: stable in continuous time, unstable sampled at 1 kHz
    r = _design(tmp_path, "--profile", prof.name, "--method", "zn", "--preset", "paper2016")
    _check_failed(r, tmp_path / "assawinchaichote2016.zn.design.failed.json", good, before)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["assawinchaichote2016.toml",
                                                          "assawinchaichote2016.zn.design.failed.json",
                                                          "assawinchaichote2016.zn.design.json"]


def test_a_failed_design_never_replaces_the_named_output(tmp_path):
    prof, good, before = _setup(tmp_path)
    r = _design(tmp_path, "--profile", str(prof), "--method", "zn", "--preset", "paper2016", "-o", str(good))
    _check_failed(r, tmp_path / "assawinchaichote2016.zn.design.failed.json", good, before)


def test_a_verified_design_replaces_a_design_file(tmp_path):
    """The other side of the gate: a verified design is written where the failed one was not."""
    prof, good, before = _setup(tmp_path)
    r = _design(tmp_path, "--profile", prof.name, "--method", "zn")
    assert r.returncode == 0, r.stdout + r.stderr
    assert f"wrote {good.name}" in r.stdout or f"wrote {good}" in r.stdout, r.stdout
    d = json.loads(good.read_text())
    assert d["status"] == "verified"
    assert not (tmp_path / "assawinchaichote2016.zn.design.failed.json").exists()


# ---------------------------------------------------------------------------
# Verified means flashable: the design's firmware built for the chip within every budget
# ---------------------------------------------------------------------------
def test_a_verified_design_carries_its_chip_build(tmp_path):
    r = _design(tmp_path, "--profile", "duy2008_halls", "--method", "zn", "-o", str(tmp_path) + "/")
    assert r.returncode == 0, r.stdout + r.stderr
    d = json.loads((tmp_path / "duy2008_halls.zn.design.json").read_text())
    assert d["status"] == "verified"
    assert d["verification"]["firmware_fits_chip"]["value"] == "fits"
    assert d["verification"]["firmware_fits_chip"]["ok"] is True
    # the figures are printed: every interrupt of the halls-only build, against its budget
    for key in ("flash ", "RAM + stack", "speed_loop_isr", "hall_isr", "uart_rx_byte"):
        assert any(ln.startswith("  chip") and key in ln for ln in r.stdout.splitlines()), (key, r.stdout)


def test_a_design_over_a_chip_budget_is_refused_with_the_figure_first(profiles, monkeypatch):
    """A budget the build exceeds (the hall interrupt's, lowered below the build's figure) fails the
    design: the blocking reason first, naming the figure and the budget."""
    import dataclasses
    from picdrive.firmware import target
    from picdrive.gate import check_chip, run_design
    prof = profiles["duy2008_halls"]
    res = run_design(prof, "zn", progress=False)
    assert res.ok, res.reasons
    monkeypatch.setattr(target, "BUDGETS", dataclasses.replace(target.BUDGETS, hall_isr_cycles=100))
    lines = check_chip(prof, res)
    assert any(ln.startswith("hall_isr") for ln in lines)
    assert not res.ok and res.status == "failed"
    assert res.reasons[0].startswith("the firmware for this design does not fit the PIC18F4431 (hall_isr ")
    assert "cycles > 100" in res.reasons[0]
    assert res.verification["firmware_fits_chip"]["ok"] is False


def test_no_chip_check_says_so_in_the_design_file(tmp_path):
    r = _design(tmp_path, "--profile", "duy2008_halls", "--method", "zn", "-o", str(tmp_path) + "/",
                "--no-chip-check")
    assert r.returncode == 0, r.stdout + r.stderr
    d = json.loads((tmp_path / "duy2008_halls.zn.design.json").read_text())
    assert d["verification"]["firmware_fits_chip"]["value"] == "not checked (--no-chip-check)"
    assert not any(ln.startswith("  chip") for ln in r.stdout.splitlines())
