"""picdrive demo: the whole chain (design -> firmware -> twin -> report) on the bundled example."""
import json
import math

from picdrive.cli import main


def test_demo_runs_the_chain_and_writes_whole_report(tmp_path, capsys):
    out = tmp_path / "demo"
    rc = main(["demo", "--method", "zn", "-o", str(out), "--step-s", "0.4", "--load-s", "0.4", "--no-progress"])
    assert rc == 0
    text = (out / "report.md").read_text()
    assert "## 3. The firmware in the twin" in text and "| zn |" in text
    for f in ("twin_runs.png", "twin_zoom.png", "twin/zn.csv", "designs/duy2008.zn.design.json",
              "firmware/zn/drive.c", "firmware/zn/link_fw.c", "firmware/zn/duy2008-zn.hex", "summary.json"):
        assert (out / f).is_file(), f
    # the firmware as 'picdrive firmware' builds it: the chip's HEX, measured against every budget
    assert "within every budget" in capsys.readouterr().out
    s = json.loads((out / "summary.json").read_text())
    m = s["twin"]["zn"]
    # the drive really moved: it rose to the target in finite time and stayed near it
    assert math.isfinite(m["rise_ms"]) and m["rise_ms"] > 0
    assert abs(m["true_final_rpm"]) > 0.5 * 2400
    assert m["dropped_samples"] == 0
    assert not list(tmp_path.glob(".demo.*")), "temporary folder left behind"


def test_demo_refuses_unknown_profile_and_leaves_nothing(tmp_path, capsys):
    out = tmp_path / "demo"
    rc = main(["demo", "--profile", "no-such-profile", "-o", str(out)])
    assert rc == 2
    assert "no profile file 'no-such-profile'" in capsys.readouterr().err
    assert not out.exists() and not list(tmp_path.iterdir())
