"""picdrive report on a reduced configuration: files written, every registered claim has its row.

The registry (picdrive.papers.claims.CLAIMS) lists every printed claim the report answers; the report
must show each one once, with a verdict, and a failed computation with its reason.
"""
import re

import pytest

from picdrive.papers import claims as reg
from picdrive.papers.report import write_report


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    out = tmp_path_factory.mktemp("rep") / "rep"
    md = write_report(out, quick=True, profiles=("duy2008",), progress=False)
    return out, md.read_text()


def test_every_registered_claim_has_its_row(report):
    _, text = report
    assert reg.check_rows(text) == []
    rows = reg.parse_rows(text)
    assert set(rows) >= {c.id for c in reg.CLAIMS}
    for c in reg.CLAIMS:
        r = rows[c.id]
        assert r["verdict"] in reg.VERDICTS
        if r["verdict"] == "failed":          # a failed computation says why
            assert len(r["reason"]) >= 10 and r["reason"] != reg.NO_COMPUTATION


def test_claim_rows_say_what_picdrive_computes(report):
    out, text = report
    rows = reg.parse_rows(text)
    for png in ("fig2016_speed.png", "fig2016_disturbance_ratio.png", "compare_duy2008.png",
                "repro2008_fig3.png", "repro2008_fig4.png"):
        assert (out / png).stat().st_size > 1000
    assert rows["2016-thm1"]["computed"].startswith("infeasible") and rows["2016-thm1"]["verdict"] == "disagree"
    m = re.search(r"Psi_1\(1,1\) = \+([0-9.]+) > 0", rows["2016-lmi13"]["computed"])
    assert m and float(m.group(1)) == pytest.approx(2.391, abs=1e-3)
    assert rows["2016-k1"]["computed"].startswith("Y_1 P^-1 = [0.6759 ")
    assert "sqrt(0.0825) = 0.2872" in rows["2016-fig7-gamma"]["computed"]
    # read literally, LMI (15) row 5 certifies a bound the loop breaks
    m = re.search(r"true H-inf norm ([0-9.e+-]+) \(([0-9.e+-]+) x\)", rows["2016-row5"]["computed"])
    assert m and float(m.group(2)) > 1.0 and rows["2016-row5"]["verdict"] == "disagree"
    # the TS model is exact: the 2400 rpm miss is not the approximation's
    assert rows["2016-miss"]["computed"].startswith("no: the TS model is exact")
    assert rows["2016-miss"]["verdict"] == "disagree"
    # Table 2: the fuzzy row is there, computed or failed with the design's reason
    fz = rows["2016-t2-fuzzy"]
    assert fz["verdict"] in ("agree", "disagree") or ("Theorem 1" in fz["reason"] or "verif" in fz["reason"])
    assert re.match(r"(inf|[0-9.]+) s / ", rows["2016-t2-pid"]["computed"])
    # 2008: model rounding agrees, Table 3 does not, the ordering does
    assert rows["2008-eq18"]["verdict"] == "agree" and rows["2008-eq19"]["verdict"] == "disagree"
    assert rows["2008-t3-prop"]["verdict"] == "disagree" and rows["2008-order"]["verdict"] == "agree"
    # beside the drive: the averaged model's speed dependence, the bench rows name their bench
    assert rows["drive-rules"]["verdict"] == "agree" and " x), k_t/Kt " in rows["drive-rules"]["computed"]
    assert "bench/scheduling.py" in rows["drive-schedule"]["reason"]
    # the comparison table has a verified fuzzy row with numbers
    assert re.search(r"\| fuzzy-hinf \(verified\) \| [0-9.]+ \| [0-9.]+ \|", text)


def test_flat_speed_trace_is_explained(report):
    _, text = report
    # the ZN PID sampled at 10 kHz sits near 0 rpm: the caption says why (read from the run)
    cap = next(line for line in text.splitlines() if line.startswith("Curves:"))
    assert re.search(r"ZN PID at 10 kHz with load: the speed stays below 1 % of 2400 rpm .*limit cycle", cap)


def test_report_folder_is_replaced_whole(report):
    out, _ = report
    md2 = write_report(out, quick=True, profiles=(), progress=False)
    assert md2.exists() and not (out / "compare_duy2008.png").exists()
    text = md2.read_text()
    # without a compared profile the rows that need one fail, with the reason, and are not dropped
    assert reg.check_rows(text) == []
    row = reg.parse_rows(text)["drive-fuzzy-vs-pid"]
    assert row["verdict"] == "failed" and "no design compared" in row["reason"]


def test_check_rows_catches_a_lost_row_a_silent_failure_and_a_missing_computation():
    c0, c1 = reg.CLAIMS[0], reg.CLAIMS[1]
    rows = [reg.evaluate(c0, lambda: ("x", "agree", "")), reg.evaluate(c1, lambda: ("y", "disagree", "z"))]
    text = "\n".join(reg.table(rows))
    assert reg.check_rows(text, (c0, c1)) == []
    lost = "\n".join(line for line in text.splitlines() if f"| {c1.id} |" not in line)
    assert reg.check_rows(lost, (c0, c1)) == [f"{c1.id}: 0 rows (claim {c1.text!r})"]
    silent = "\n".join(reg.table([rows[0], reg.Row(c1, "failed", "failed", "")]))
    assert reg.check_rows(silent, (c0, c1)) == [f"{c1.id}: failed without a reason"]
    missing = "\n".join(reg.table([rows[0], reg.evaluate(c1, None)]))
    assert reg.check_rows(missing, (c0, c1)) == [f"{c1.id}: the report has no computation for it"]


def test_a_raising_computation_is_a_failed_row_with_its_message():
    def boom():
        raise ValueError("solver gave up at disk 804 rad/s")
    r = reg.evaluate(reg.CLAIMS[0], boom)
    assert (r.verdict, r.computed, r.reason) == ("failed", "failed", "ValueError: solver gave up at disk 804 rad/s")
    r = reg.evaluate(reg.CLAIMS[0], lambda: ("x", "maybe", ""))
    assert r.verdict == "failed" and "'maybe'" in r.reason


def test_registry_has_one_copy_of_each_claim():
    ids = [c.id for c in reg.CLAIMS]
    assert len(ids) == len(set(ids))
    assert len({(c.paper, c.text) for c in reg.CLAIMS}) == len(ids)
    assert {c.paper for c in reg.CLAIMS} == {"2016", "2008", "2016 vs drive"}
