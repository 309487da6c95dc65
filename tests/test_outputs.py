"""The output rule (docs/outputs.md, picdrive.outputs): picdrive never removes what it did not write.

Through the commands (``python -m picdrive``, a subprocess each) where the rule shows at the command
line, and through :mod:`picdrive.outputs` for the cases that need a written folder to start from.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from picdrive import outputs
from picdrive.paths import repo_root

ROOT = repo_root()
ENV = {**os.environ, "PYTHONPATH": os.pathsep.join(str(ROOT / d) for d in ("host", "hil")), "MPLBACKEND": "Agg"}
DESIGN = str(ROOT / "examples" / "duy2008.zn.design.json")


def picdrive(cwd: Path, *argv: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "picdrive", *argv], cwd=cwd, env=ENV,
                          capture_output=True, text=True, timeout=300)


def _user_folder(d: Path) -> Path:
    (d / "sub").mkdir(parents=True)
    (d / "notes.txt").write_text("mine")
    (d / "sub" / "data.csv").write_text("1,2\n")
    return d


def test_firmware_into_a_folder_with_an_unrelated_file_and_a_subfolder_leaves_both(tmp_path):
    mine = _user_folder(tmp_path / "mine")
    r = picdrive(tmp_path, "firmware", "--no-hex", "--profile", "duy2008", "--design", DESIGN, "-o", "mine")
    assert r.returncode == 2 and "not written by picdrive" in r.stderr, r.stderr
    assert (mine / "notes.txt").read_text() == "mine" and (mine / "sub" / "data.csv").read_text() == "1,2\n"
    assert sorted(p.name for p in mine.iterdir()) == ["notes.txt", "sub"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mine"]          # no temporary folder left


def test_a_file_is_not_replaced_by_a_folder(tmp_path):
    (tmp_path / "fw").write_text("a file of mine")
    r = picdrive(tmp_path, "firmware", "--no-hex", "--profile", "duy2008", "--design", DESIGN, "-o", "fw")
    assert r.returncode == 2 and "fw exists and is not a folder" in r.stderr, r.stderr
    assert (tmp_path / "fw").read_text() == "a file of mine"


def test_the_marker_lets_picdrive_replace_its_own_output_and_only_that(tmp_path):
    r = picdrive(tmp_path, "firmware", "--no-hex", "--profile", "duy2008", "--design", DESIGN, "-o", "fw")
    assert r.returncode == 0, r.stderr
    fw = tmp_path / "fw"
    man = json.loads((fw / outputs.MARKER).read_text())
    assert man["schema"] == "picdrive.output/1" and "drive.c" in man["files"] and man["regenerable"] == ["build"]
    (fw / "build").mkdir()
    (fw / "build" / "duy2008.hex").write_text(":00000001FF\n")           # what make leaves: regenerable
    (fw / "drive.c").unlink()                                          # a file picdrive wrote, removed: fine
    r = picdrive(tmp_path, "firmware", "--no-hex", "--profile", "duy2008", "--design", DESIGN, "-o", "fw")
    assert r.returncode == 0, r.stderr
    assert (fw / "drive.c").is_file() and not (fw / "build").exists()
    # a file the user added to picdrive's folder stops the replacement, and survives
    (fw / "my_notes.txt").write_text("tuning notes")
    r = picdrive(tmp_path, "firmware", "--no-hex", "--profile", "duy2008", "--design", DESIGN, "-o", "fw")
    assert r.returncode == 2 and "my_notes.txt" in r.stderr, r.stderr
    assert (fw / "my_notes.txt").read_text() == "tuning notes"


def test_a_marker_alone_does_not_make_a_folder_picdrives(tmp_path):
    d = _user_folder(tmp_path / "d")
    (d / outputs.MARKER).write_text(outputs.manifest_text("firmware", {"drive.c": "x"}))
    with pytest.raises(outputs.OutputError, match=r"holds files picdrive did not write \(notes.txt, sub/data.csv\)"):
        outputs.dir_output(d)
    (d / outputs.MARKER).write_text("not json")
    with pytest.raises(outputs.OutputError, match="not a marker picdrive can read"):
        outputs.dir_output(d)


def test_missing_folders_are_created_the_same_way_by_every_command(tmp_path):
    # design: -o newdir/ (missing, trailing slash) is a folder, created; the file goes inside
    r = picdrive(tmp_path, "design", "--profile", "duy2008", "--method", "zn", "--no-progress", "-o", "new/deeper/")
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "new" / "deeper" / "duy2008.zn.design.json").is_file()
    assert not (tmp_path / "new" / "deeper").is_file()
    # design -o into an existing design file replaces it (picdrive's own kind of file)
    r = picdrive(tmp_path, "design", "--profile", "duy2008", "--method", "zn", "--no-progress",
                 "-o", "new/deeper/duy2008.zn.design.json")
    assert r.returncode == 0, r.stderr
    # firmware: missing parents are created too
    r = picdrive(tmp_path, "firmware", "--no-hex", "--profile", "duy2008", "--design",
                 str(tmp_path / "new" / "deeper" / "duy2008.zn.design.json"), "-o", "a/b/fw/")
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "a" / "b" / "fw" / "drive.c").is_file()
    # and into an existing empty folder
    (tmp_path / "empty").mkdir()
    r = picdrive(tmp_path, "firmware", "--no-hex", "--profile", "duy2008", "--design", DESIGN, "-o", "empty")
    assert r.returncode == 0 and (tmp_path / "empty" / outputs.MARKER).is_file(), r.stderr


def test_file_output_rules(tmp_path):
    default = Path("p.zn.design.json")
    assert outputs.file_output(str(tmp_path / "x") + "/", default) == tmp_path / "x" / default.name
    assert not (tmp_path / "x").exists()                                 # checked, nothing made yet
    (tmp_path / "d").mkdir()
    assert outputs.file_output(tmp_path / "d", default) == tmp_path / "d" / default.name
    (tmp_path / "f.json").write_text("{}")
    with pytest.raises(outputs.OutputError, match="not a file picdrive wrote"):
        outputs.file_output(tmp_path / "f.json", default)
    assert outputs.file_output(tmp_path / "f.json", default, same_kind=lambda p: True) == tmp_path / "f.json"
    os.mkfifo(tmp_path / "fifo")
    with pytest.raises(outputs.OutputError, match="not a regular file"):
        outputs.file_output(tmp_path / "fifo", default, same_kind=lambda p: True)


def test_unwritable_destinations_are_refused_before_the_work(tmp_path):
    for bad, why in (("/proc/picdrive-x/fw", "cannot write in /proc"), ("/sys/picdrive-x", "cannot write in /sys")):
        with pytest.raises(outputs.OutputError, match=why):
            outputs.dir_output(bad)
    (tmp_path / "file").write_text("x")
    with pytest.raises(outputs.OutputError, match="is a file, not a folder"):
        outputs.dir_output(tmp_path / "file" / "sub" / "fw")
    with pytest.raises(outputs.OutputError, match="is a file, not a folder"):
        outputs.file_output(tmp_path / "file" / "d.json", Path("d.json"))
    if os.geteuid() != 0:                      # root passes permission bits: only /proc and /sys refuse it
        ro = tmp_path / "ro"
        ro.mkdir(mode=0o500)
        with pytest.raises(outputs.OutputError, match="Permission denied"):
            outputs.dir_output(ro / "fw")


def test_a_failed_write_leaves_nothing_half_written(tmp_path, monkeypatch):
    from picdrive import fileio
    out = tmp_path / "rep"
    tmp = outputs.new_temp_dir(out)
    (tmp / "report.md").write_text("new")

    def fail(a, b):
        raise OSError(28, "No space left on device")
    monkeypatch.setattr(fileio, "publish_dir", fail)
    with pytest.raises(outputs.OutputError, match="No space left on device"):
        outputs.publish_dir(tmp, out, "report")
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_report_and_demo_refuse_a_user_folder_before_working(tmp_path):
    mine = _user_folder(tmp_path / "mine")
    for cmd in ("report", "demo"):
        r = picdrive(tmp_path, cmd, "-o", "mine")
        assert r.returncode == 2 and "not written by picdrive" in r.stderr, r.stderr
        assert sorted(p.name for p in mine.iterdir()) == ["notes.txt", "sub"]
