"""picdrive report on a reduced configuration: files written, claim tables present and computed."""
import re

import pytest

from picdrive.papers.report import write_report


@pytest.mark.timeout(400)
def test_report_quick(tmp_path):
    out = tmp_path / "rep"
    md = write_report(out, quick=True, profiles=("assawinchaichote2016",), progress=False)
    text = md.read_text()
    assert (out / "fig2016_speed.png").stat().st_size > 1000
    assert (out / "fig2016_disturbance_ratio.png").stat().st_size > 1000
    assert (out / "compare_assawinchaichote2016.png").stat().st_size > 1000
    # the 2016 claims, each with a computed value
    assert "| Theorem 1 feasible at gamma = delta = 1, alpha = 2 (printed model) | yes (P, Y_j printed) | infeasible |" in text
    m = re.search(r"Psi_1\(1,1\) = \+([0-9.]+) > 0", text)
    assert m and float(m.group(1)) == pytest.approx(2.391, abs=1e-3)
    assert "sqrt(0.0825) = 0.2872" in text
    assert re.search(r"\| K_1 = Y_1 P\^-1 \| \[0\.9577 .*\| \[0\.6759 ", text)
    # every printed claim has its row, computed or marked failed with a reason (none is dropped)
    from picdrive.papers.repro2016 import CLAIMS
    for claim in CLAIMS:
        assert re.search(r"^\| " + re.escape(claim) + r"[ (|]", text, re.M), f"report lost the row {claim!r}"
    m = re.search(r"^\| LMI \(15\) row 5 read as printed .*true H-inf norm ([0-9.e+-]+) \(([0-9.e+-]+) x\)", text, re.M)
    assert m and float(m.group(2)) > 1.0          # read literally, the LMI certifies a bound the loop breaks
    assert re.search(r"^\| the 2400 rpm miss is due to the fuzzy approximation \| yes \| no: the TS model is exact", text, re.M)
    assert re.search(r"^\| Table 2 H-inf fuzzy: settling / overshoot \| 0\.04 s / no overshoot \| ([0-9.]+ s|failed: .+\| .+)", text, re.M)
    # the comparison table has a verified fuzzy row with numbers
    assert re.search(r"\| fuzzy-hinf \(verified\) \| [0-9.]+ \| [0-9.]+ \|", text)
    # rewriting replaces the folder whole
    md2 = write_report(out, quick=True, profiles=(), progress=False)
    assert md2.exists() and not (out / "compare_assawinchaichote2016.png").exists()
