"""The paper's claims and every pair of strategies, read on the grid's runs (deploy/studies/grid_report.py) by
the rule of common/analysis/across_seeds.py: a run scored by its chosen policy's test CFR per test start.

A claim the runs contradict (the worse group ahead) is also read the other way round, with the two-sided
p-value, since that direction is chosen after seeing them. The pairs whose interval of P(first > second) lies
wholly off 0.5 are listed, the farthest first, with the command that adds seeds 3 and 4 of the first.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Sequence

import numpy as np

from common.analysis import across_seeds
from common.analysis.intervals import Bootstrap
from common.exploration.names import STRATEGIES

if TYPE_CHECKING:
    from deploy.studies.grid_report import CELL, GridRun

LEADERS = ("vdbe_softmax", "bmc")
CLAIMS = (
    ("1", "Softmax, MBE, VDBE-Softmax and BMC beat constant and decreasing epsilon-greedy",
     ("softmax", "max_boltzmann", "vdbe_softmax", "bmc"), ("constant", "decreasing")),
    ("2", "VDBE-Softmax and BMC lead at buffer 1,000 (against the other five)",
     LEADERS, tuple(name for name in STRATEGIES if name not in LEADERS)),
)


def claim_readings(runs: Sequence[GridRun], bootstrap: Bootstrap,
                   cells: Sequence[CELL] = ((1000, "paper"),)) -> list[dict]:
    """The paper's claims on the runs of these cells pooled (by default the paper's learner at buffer 1,000):
    each group of strategies pooled, a run scored by its chosen policy's test CFR per start."""
    readings = []
    for number, text, better, worse in CLAIMS:
        groups = [[item.start_cfr for item in runs if item.cell in cells and item.run.strategy in side]
                  for side in (better, worse)]
        if not all(groups):
            readings.append({"claim": number, "text": text, "reading": "not asked (a side has no runs)"})
            continue
        better_runs, worse_runs = (np.vstack(group) for group in groups)
        found = across_seeds.claim(better_runs, worse_runs, bootstrap)
        readings.append({"claim": number, "text": text, "reading": found.reading, "p_value": found.p_value,
                         "runs": f"{found.a_runs} vs {found.b_runs}", "improvement": found.improvement.point,
                         "improvement_low": found.improvement.interval.low,
                         "improvement_high": found.improvement.interval.high,
                         "smallest_p": across_seeds.smallest_p_value(found.a_runs, found.b_runs)})
        if found.improvement.point < across_seeds.NO_IMPROVEMENT:
            readings[-1]["reverse"] = across_seeds.reverse_claim(better_runs, worse_runs, bootstrap)
    return readings


def pair_readings(runs: Sequence[GridRun], bootstrap: Bootstrap, cell: CELL = (1000, "paper")) -> list[dict]:
    """Every two strategies of a cell: P(first > second) with its interval (no claim: see seeds_to_support)."""
    by_strategy = {name: np.vstack([item.start_cfr for item in runs if item.cell == cell and item.run.strategy == name])
                   for name in STRATEGIES if any(item.cell == cell and item.run.strategy == name for item in runs)}
    rows = []
    for first in by_strategy:
        for second in by_strategy:
            if STRATEGIES.index(first) < STRATEGIES.index(second):
                found = across_seeds.improvement_estimate(by_strategy[first], by_strategy[second], bootstrap)
                rows.append({"first": first, "second": second, "improvement": found.point,
                             "low": found.interval.low, "high": found.interval.high,
                             "runs": (len(by_strategy[first]), len(by_strategy[second]))})
    return rows


def pairs_off_even(pairs: Sequence[dict]) -> list[dict]:
    """The pairs whose interval of P(first > second) lies wholly off 0.5, the farthest first: where seeds 3 and
    4 could turn a lean into a finding."""
    def margin(row: dict) -> float:
        return max(row["low"] - across_seeds.NO_IMPROVEMENT, across_seeds.NO_IMPROVEMENT - row["high"])
    return sorted((row for row in pairs if row["runs"] != (1, 1) and margin(row) > 0), key=margin, reverse=True)


def claims_lines(runs: Sequence[GridRun], bootstrap: Bootstrap) -> list[str]:
    """The report's section on the paper's claims and the pairs."""
    lines = [_rule_text(), ""]
    for label, cells in claim_cells(runs):
        lines += ([f"{label}:", ""] if label else []) + _reading_lines(claim_readings(runs, bootstrap, cells))
        lines += [""] if label else []
    lines += ["", f"A claim about one pair of strategies needs {across_seeds.seeds_to_support()} seeds a side: with "
              f"3 against 3 the least one-sided p-value is {across_seeds.smallest_p_value(3, 3):.2f}, not below "
              f"{across_seeds.SIGNIFICANCE}. Every pair's probability of improvement, as a guide:", "",
              "| First | Second | P(first > second) [CI] |", "|---|---|---:|"]
    pairs = pair_readings(runs, bootstrap)
    for row in pairs:
        interval = "(one run each)" if row["runs"] == (1, 1) else f"[{row['low']:.2f}, {row['high']:.2f}]"
        lines.append(f"| {row['first']} | {row['second']} | {row['improvement']:.2f} {interval} |")
    return lines + ["", *more_seeds_lines(pairs_off_even(pairs))]


def claim_cells(runs: Sequence[GridRun]) -> list[tuple[str, tuple[CELL, ...]]]:
    """The cells the claims are read on: buffer 1,000 alone where the grid has no other buffer; else each
    buffer of the paper's learner, then all of them pooled (strategy group x buffer), each with its label."""
    buffers = sorted({item.run.capacity for item in runs if item.run.options == "paper"})
    if buffers in ([], [1000]):
        return [("", ((1000, "paper"),))]
    cells = [(f"At buffer {buffer:,d}", ((buffer, "paper"),)) for buffer in buffers]
    return cells + [("Both buffers pooled (each group's runs at every buffer)",
                     tuple((buffer, "paper") for buffer in buffers))]


def _reading_lines(readings: Sequence[dict]) -> list[str]:
    lines = []
    for reading in readings:
        if "p_value" not in reading:
            lines.append(f"- Claim {reading['claim']} ({reading['text']}): {reading['reading']}.")
            continue
        lines.append(f"- Claim {reading['claim']} ({reading['text']}): **{reading['reading']}**; runs "
                     f"{reading['runs']}, one-sided Mann-Whitney p = {reading['p_value']:.4f} (the least these "
                     f"runs can give: {reading['smallest_p']:.2g}), P(better > worse) = {reading['improvement']:.3f} "
                     f"[{reading['improvement_low']:.3f}, {reading['improvement_high']:.3f}].")
        if "reverse" in reading:
            lines.append(_reverse_text(reading["reverse"]))
    return lines


def _reverse_text(found: across_seeds.Claim) -> str:
    return (f"  - The other way round (the worse group ahead, read after the fact): **{found.reading}**; "
            f"two-sided p = {found.p_value:.4f}, P(worse > better) = {found.improvement.point:.3f} "
            f"[{found.improvement.interval.low:.3f}, {found.improvement.interval.high:.3f}].")


def more_seeds_lines(pairs: Sequence[dict]) -> list[str]:
    if not pairs:
        return ["No pair's interval lies off 0.5: no pair leans enough to be worth more seeds yet."]
    order = [f"{row['first']} {'>' if row['improvement'] > across_seeds.NO_IMPROVEMENT else '<'} {row['second']}"
             for row in pairs]
    first = pairs[0]
    return [f"Pairs whose interval lies off 0.5, the farthest first: {'; '.join(order)}. Seeds 3 and 4 of the first "
            f"(5 a side; the least p-value {across_seeds.smallest_p_value(5, 5):.4f}): `.venv/bin/python "
            f"deploy/grid/experiments.py --strategies {first['first']},{first['second']} --buffers 1000 "
            f"--seeds 3,4`."]


def _rule_text() -> str:
    return (f"The rule (common/analysis/across_seeds.py): a claim is supported when the one-sided Mann-Whitney "
            f"test of the better group's runs against the worse group's gives p < {across_seeds.SIGNIFICANCE} and "
            f"the interval of P(better > worse) lies above {across_seeds.NO_IMPROVEMENT}; a lean when only the "
            f"point estimate of P(better > worse) is above {across_seeds.NO_IMPROVEMENT}; can't tell otherwise. "
            "A run's score is its chosen policy's test CFR per test start; P is averaged over the starts, and "
            "the test reads each run's mean over them.")
