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
