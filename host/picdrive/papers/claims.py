"""The registry of the claims ``picdrive report`` answers: one entry per printed claim, one copy of each.

:data:`CLAIMS` lists every printed claim of the two papers that the report reproduces (paper ``2016``:
Assawinchaichote & Chayaopas; ``2008``: Duy et al.) and the 2016 paper's fuzzy claims set beside what
picdrive measured on the six-step drive (paper ``2016 vs drive``).  The report renders each one
as one table row (:func:`table`)::

    | id | claim (as printed) | printed | picdrive | verdict | why |

with the verdict (:data:`VERDICTS`) ``agree``, ``disagree``, ``failed`` (the computation raised or its
verification failed: the reason is the exception's message or the failed check) or ``bench`` (too slow
for the report: the reason names the ``bench/`` script that prints it).  :func:`evaluate` turns a
computation into a row, a raised exception into a failed row, so no claim is ever dropped;
:func:`check_rows` lists what a written report lacks (tests/test_report.py).
"""
from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Callable, Iterable

__all__ = ["Claim", "Row", "CLAIMS", "VERDICTS", "NO_OVERSHOOT_PCT", "NO_COMPUTATION", "claims_of", "evaluate",
           "rows_for", "table", "parse_rows", "check_rows", "once"]

VERDICTS = ("agree", "disagree", "failed", "bench")
#: overshoot (%) below which a printed "no overshoot" counts as met
NO_OVERSHOOT_PCT = 0.1
#: the reason of a claim the report has no computation for (:func:`check_rows` flags it: a lost row)
NO_COMPUTATION = "no computation registered for this claim"


@dataclass(frozen=True)
class Claim:
    """One printed claim: stable id, paper, where it is printed, the claim and the printed value (text)."""

    id: str
    paper: str
    where: str
    text: str
    printed: str


@dataclass(frozen=True)
class Row:
    """A claim answered: what picdrive computes, the verdict and why."""

    claim: Claim
    computed: str
    verdict: str
    reason: str


def _c(id_, paper, where, text, printed) -> Claim:
    return Claim(id_, paper, where, text, printed)


CLAIMS: tuple[Claim, ...] = (
    # --- 2016: Theorem 1 and its example (sec. 6)
    _c("2016-thm1", "2016", "sec. 6", "Theorem 1 is feasible at gamma = delta = 1, alpha = 2 (model as printed)",
       "yes: P, Y_1, Y_2 printed"),
    _c("2016-lmi13", "2016", "sec. 6, eq 13", "the printed P satisfies LMI (13)", "implied"),
    _c("2016-k1", "2016", "sec. 6, eq 17", "K_1 = Y_1 P^-1", "K_1 as printed"),
    _c("2016-k2", "2016", "sec. 6, eq 17", "K_2 = Y_2 P^-1", "K_2 as printed"),
    _c("2016-stable", "2016", "sec. 6", "the printed K_j stabilise every A_i + B_i K_j", "implied by Theorem 1"),
    _c("2016-gamma-delta1", "2016", "sec. 6", "gamma = 1 is reached with delta = 1 (model corrected)",
       "gamma = 1 feasible"),
    _c("2016-gamma-free", "2016", "Theorem 1", "an H-inf fuzzy controller with gamma <= 1 exists (delta free)",
       "gamma = 1"),
    _c("2016-row5", "2016", "eq 15, row 5", "LMI (15) with B_w in row 5 certifies the L2 gain (9)", "B_w"),
    _c("2016-miss", "2016", "Remark 1", "the speed misses 2400 rpm because the TS model only approximates the motor",
       "fuzzy approximation"),
    _c("2016-fig7", "2016", "Fig. 7", "after 0.2 s the energy ratio int z^2 / int w^2 is about 0.096",
       "about 0.096"),
    _c("2016-fig7-gamma", "2016", "Remark 1", "gamma = sqrt(0.0825) = 0.2864", "0.2864"),
    _c("2016-fig7-below", "2016", "Remark 1", "the achieved gain is below the prescribed gamma = 1", "0.2864 < 1"),
    _c("2016-t2-fuzzy", "2016", "Table 2", "H-inf fuzzy, 2400 rpm with load: settling / overshoot",
       "0.04 s / none"),
    _c("2016-t2-pid", "2016", "Table 2", "ZN PID (Kp 0.43, Ki 2.30, Kd 0.28), 2400 rpm with load: settling / overshoot",
       "0.22 s / 4.16 %"),
    _c("2016-faster", "2016", "sec. 7", "the H-inf fuzzy controller responds faster than the PID, without overshoot",
       "faster, no overshoot"),
    # --- 2008: model, GA, Table 3, Figure 4
    _c("2008-eq18", "2008", "eq 18", "nominal plant 275577.36 / (s^2 + 417.7 s + 43567.5) from Table 2",
       "275577.36; 417.7; 43567.5"),
    _c("2008-eq19", "2008", "eq 19", "|xi(jw)| <= 0.1 |d| for all w", "<= 0.01 (d = 0.1)"),
    _c("2008-eq20", "2008", "eq 20", "closed-loop polynomial s^3 + (417.7 + K kd) s^2 + (43567.5 + K kp) s + K ki",
       "formulas"),
    _c("2008-eq23", "2008", "eq 23", "perturbed plant denominator", "1, 417.8, 43619.27, 8533.75, 435675"),
    _c("2008-eq24", "2008", "eq 24", "perturbed closed-loop coefficients c4..c0", "formulas"),
    _c("2008-eq25", "2008", "eq 25", "eq 25 numerator", "1, 417.8, 43619, 8533.8, 435675"),
    _c("2008-eq6", "2008", "eq 6", "load gains k_pl = R/(Kb Kt), k_dl = L/(Kb Kt)", "1032; 2.53"),
    _c("2008-eq21", "2008", "eqs 21, 25", "eq 21 and eq 25 are both the unit-step tracking error",
       "unit step"),
    _c("2008-eq17", "2008", "eq 17", "fitness F = -E for feasible chromosomes, 0 otherwise (maximised)",
       "F = -E / 0"),
    _c("2008-constraint", "2008", "sec. 5", "the GA gains meet the robust constraint (eq 6) with d = 0.1", "<= 1"),
    _c("2008-ga", "2008", "sec. 5", "the GA (200 x 20) gives the minimum-J3 gains kp 180.1755, ki 4.6997, kd 0.0353",
       "J3 minimum"),
    _c("2008-t3-yh", "2008", "Table 3", "Yu & Hwang LQR PID: rise / settling / overshoot", "0.84 ms / 1.58 ms / 1.48 %"),
    _c("2008-t3-prop", "2008", "Table 3", "proposed PID: rise / settling / overshoot", "0.59 ms / 1.07 ms / 0.58 %"),
    _c("2008-order", "2008", "Table 3", "the proposed PID is faster than Yu & Hwang's", "faster"),
    _c("2008-fig4", "2008", "Fig. 4", "d does not have much influence on the output", "little influence"),
    _c("2008-pic", "2008", "sec. 5, Fig. 9", "the proposed PID on the PIC18F4431 drive tracks a step reference well",
       "tracks well"),
    # --- 2016's fuzzy claims beside what picdrive measured on the six-step drive
    _c("drive-rules", "2016 vs drive", "sec. 4, 6",
       "the motor's dynamics change with speed: two TS rules at N1 = 0, N2 = 3000 differ", "A_1 != A_2"),
    _c("drive-model", "2016 vs drive", "sec. 3, 6", "the drive's dynamics are those of the motor's equations (5), (36), "
       "which the TS rules represent", "eqs 5, 36"),
    _c("drive-schedule", "2016 vs drive", "sec. 7", "scheduling the gains on the speed (two rules) gives a better "
       "response than one fixed controller", "better"),
    _c("drive-fuzzy-vs-pid", "2016 vs drive", "sec. 7, Table 2", "the H-inf fuzzy design responds faster than the "
       "PID, without overshoot", "faster, no overshoot"),
    _c("drive-fast", "2016 vs drive", "Table 2", "the fuzzy loop settles fast (0.04 s): how near the bridge's own "
       "fastest step", "0.04 s"),
)


def claims_of(paper: str) -> tuple[Claim, ...]:
    """The registered claims of one paper (``2016``, ``2008``, ``2016 vs drive``), in order."""
    return tuple(c for c in CLAIMS if c.paper == paper)


def _one_line(s: str) -> str:
    return " ".join(str(s).split())


def evaluate(claim: Claim, compute: Callable[[], tuple[str, str, str]] | None) -> Row:
    """``compute() -> (computed, verdict, reason)`` as a row; an exception (or no computation) gives a
    failed row whose reason is the exception's type and message."""
    if compute is None:
        return Row(claim, "failed", "failed", NO_COMPUTATION)
    try:
        computed, verdict, reason = compute()
    except Exception as e:        # the report shows a failed computation, it never drops its row
        return Row(claim, "failed", "failed", _one_line(f"{type(e).__name__}: {e}") or type(e).__name__)
    if verdict not in VERDICTS:
        return Row(claim, _one_line(computed), "failed", f"computation returned the verdict {verdict!r}")
    return Row(claim, _one_line(computed), verdict, _one_line(reason))


def rows_for(paper: str, computations: dict[str, Callable[[], tuple[str, str, str]]]) -> list[Row]:
    """One row per registered claim of ``paper`` (:func:`evaluate`), in the registry's order."""
    return [evaluate(c, computations.get(c.id)) for c in claims_of(paper)]


def _cell(s: str) -> str:
    return _one_line(s).replace("|", "/")


def table(rows: Iterable[Row]) -> list[str]:
    """The rows as a Markdown table (lines)."""
    out = ["| id | claim (as printed) | printed | picdrive | verdict | why |", "|---|---|---|---|---|---|"]
    for r in rows:
        c = r.claim
        out.append(f"| {c.id} | {_cell(c.text)} ({_cell(c.where)}) | {_cell(c.printed)} | {_cell(r.computed)} | "
                   f"**{r.verdict}** | {_cell(r.reason)} |")
    return out


_ROW = re.compile(r"^\| (?P<id>[\w.-]+) \| (?P<text>.*?) \| (?P<printed>.*?) \| (?P<computed>.*?) \| "
                  r"\*\*(?P<verdict>\w+)\*\* \| (?P<reason>.*?) \|$", re.M)


def parse_rows(markdown: str) -> dict[str, dict]:
    """The claim rows of a report (by id)."""
    return {m["id"]: m.groupdict() for m in _ROW.finditer(markdown)}


def check_rows(markdown: str, claims: Iterable[Claim] = CLAIMS) -> list[str]:
    """What a report lacks: registered claims without their row (or with it twice), rows with an unknown
    verdict, failed rows without a reason, rows without a computation, bench rows that name no bench script."""
    found = parse_rows(markdown)
    problems = []
    for c in claims:
        n = len([m for m in _ROW.finditer(markdown) if m["id"] == c.id])
        if n != 1:
            problems.append(f"{c.id}: {n} rows (claim {c.text!r})")
            continue
        r = found[c.id]
        if not r["text"].startswith(_cell(c.text)):
            problems.append(f"{c.id}: row does not state the claim as registered")
        if r["verdict"] not in VERDICTS:
            problems.append(f"{c.id}: verdict {r['verdict']!r}")
        if r["verdict"] == "failed" and len(r["reason"].strip()) < 10:
            problems.append(f"{c.id}: failed without a reason")
        if r["reason"].strip() == NO_COMPUTATION:
            problems.append(f"{c.id}: the report has no computation for it")
        if r["verdict"] == "bench" and not re.search(r"bench/\w+\.py", r["reason"]):
            problems.append(f"{c.id}: bench row names no bench script")
    return problems


def once(fn: Callable):
    """``fn()`` run on the first call; later calls return its result, or raise its exception again (each
    claim that needs a failed computation then shows it as failed, with the message)."""
    box: list = []

    def call():
        if not box:
            try:
                box.append((True, fn()))
            except Exception as e:
                box.append((False, e))
        ok, v = box[0]
        if not ok:
            raise v
        return v
    return call
