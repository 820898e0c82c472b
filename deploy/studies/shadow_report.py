"""The shadow policies read side by side (issue 59): per exported grid run and policy kind, the late curve and the
chosen policy's evaluation; paired across the runs, each kind against the online one; and the kind to ship by a
rule stated before any reading.

    .venv/bin/python deploy/studies/shadow_report.py results/grid/runs --out results/grid/shadows

Per run and kind (online, target, ema; mean at its choice point only):
  late curve    the greedy test CFR of the kind's policies read from 20,000 updates on (K = 5): mean and least,
                and the same on the train starts
  chosen        the test and train CFR of the kind's chosen policy at K = 10 (evaluation/, evaluation-<kind>/)
Paired across the runs that read both, for each kind against online: the Wilcoxon signed-rank test (two-sided)
and P(kind > online) with a bootstrap interval stratified by strategy, on the chosen test CFR and on the late
curve's mean test CFR (common/analysis/paired.py).

THE RULE, stated on 2026-12-07 before any run kept a shadow policy, on the train starts only: the kind shipped
is the one whose chosen policies read the highest mean train CFR at K = 10 over the runs that read every kind;
a tie goes to the highest mean of the late curve's least train CFR (the mean kind has no late curve: it counts
as its chosen train CFR there), then to online, the paper's. Test readings never choose.
"""

from __future__ import annotations

import argparse
import csv
import statistics
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

from actor.evaluation.curve import CURVE_CSV, late_curves, read_curve
from common.analysis.intervals import Bootstrap
from common.analysis.paired import paired_improvement_estimate, signed_rank_p
from common.analysis.tables import SUMMARY_CSV
from common.run_dir import POLICY_KINDS
from deploy.grid.grid_cells import read_choice
from deploy.studies.run_results import ExportedRun, collect

READINGS_CSV = "shadow_runs.csv"
PAGE = "shadows.md"


@dataclass(frozen=True)
class KindReading:
    run: str
    strategy: str
    kind: str
    late_test_mean: float | None  # None: no late curve (the mean kind)
    late_test_min: float | None
    late_train_mean: float | None
    late_train_min: float | None
    chosen_updates: int
    chosen_test_cfr: float
    chosen_train_cfr: float


def greedy_cfr(summary_csv: Path, start_set: str) -> float:
    with summary_csv.open(newline="") as handle:
        return next(float(row["cfr"]) for row in csv.DictReader(handle)
                    if row["policy"] == "greedy" and row["start_set"] == start_set)


def run_readings(run: ExportedRun) -> list[KindReading]:
    """The readings of every kind the run chose and evaluated; [] for a run without shadows."""
    choice = read_choice(run.layout)
    if choice is None or not choice.get("kinds"):
        return []
    rows = read_curve(run.folder / "curve" / CURVE_CSV, kind=None)
    test = late_curves(rows)
    train = late_curves([{**row, "start_set": "test"} for row in rows if row["start_set"] == "train"])
    readings = []
    for kind in ["online", *choice["kinds"]]:
        summary = run.layout.evaluation_of(kind) / SUMMARY_CSV
        if not summary.is_file():
            continue
        chosen = choice if kind == "online" else choice["kinds"][kind]
        late, late_train = test.get(kind, {}), train.get(kind, {})
        readings.append(KindReading(run.name, run.strategy, kind, late.get("test_cfr_mean"), late.get("test_cfr_min"),
                                    late_train.get("test_cfr_mean"), late_train.get("test_cfr_min"),
                                    chosen["updates"], greedy_cfr(summary, "test"), greedy_cfr(summary, "train")))
    return readings


def complete(readings: Sequence[KindReading]) -> dict[str, dict[str, KindReading]]:
    """By run, by kind: the runs that read every kind any run read."""
    kinds = {reading.kind for reading in readings}
    by_run: dict[str, dict[str, KindReading]] = {}
    for reading in readings:
        by_run.setdefault(reading.run, {})[reading.kind] = reading
    return {run: of_run for run, of_run in by_run.items() if set(of_run) == kinds}


def shipped_kind(readings: Sequence[KindReading]) -> str:
    """THE RULE of the module docstring."""
    runs = complete(readings)
    if not runs:
        raise ValueError("no run read every kind: nothing to choose by")
    kinds = [kind for kind in POLICY_KINDS if kind in next(iter(runs.values()))]

    def score(kind: str) -> tuple[float, float, bool]:
        of_kind = [runs[run][kind] for run in runs]
        floor = [r.late_train_min if r.late_train_min is not None else r.chosen_train_cfr for r in of_kind]
        return (statistics.mean(r.chosen_train_cfr for r in of_kind), statistics.mean(floor), kind == "online")

    return max(kinds, key=score)


def paired_lines(readings: Sequence[KindReading], bootstrap: Bootstrap) -> list[str]:
    runs = complete(readings)
    lines = []
    for kind in [kind for kind in POLICY_KINDS[1:] if runs and kind in next(iter(runs.values()))]:
        for label, value in (("chosen policy's test CFR (K = 10)", lambda r: r.chosen_test_cfr),
                             ("late curve's mean test CFR (K = 5)", lambda r: r.late_test_mean)):
            pairs = [(value(of_run[kind]), value(of_run["online"]), of_run[kind].strategy) for of_run in runs.values()
                     if value(of_run[kind]) is not None and value(of_run["online"]) is not None]
            if not pairs:
                continue
            x, y, strata = zip(*pairs)
            estimate = paired_improvement_estimate(x, y, strata, bootstrap)
            lines.append(f"- {kind} against online, {label}, {len(pairs)} runs: Wilcoxon two-sided p = "
                         f"{signed_rank_p(x, y):.3f}; P({kind} > online) = {estimate.point:.3f} "
                         f"[{estimate.interval.low:.3f}, {estimate.interval.high:.3f}]")
    return lines


def _percent(value: float | None) -> str:
    return "–" if value is None else f"{100 * value:.0f}%"


def report_lines(readings: Sequence[KindReading], bootstrap: Bootstrap) -> list[str]:
    lines = ["# Shadow policies: does a policy that holds change what the grid ships?", "",
             "The rule (stated before the readings, train starts only): " + __doc__.split("THE RULE, ")[1].split(
                 "\n\n")[0].replace("\n", " "), "",
             "| run | kind | late test CFR mean | late test CFR least | late train CFR least | chosen | test CFR (K = 10) "
             "| train CFR (K = 10) |", "|---|---|---|---|---|---|---|---|"]
    for r in readings:
        lines.append(f"| {r.run} | {r.kind} | {_percent(r.late_test_mean)} | {_percent(r.late_test_min)} | "
                     f"{_percent(r.late_train_min)} | {r.chosen_updates:,d} | {_percent(r.chosen_test_cfr)} | "
                     f"{_percent(r.chosen_train_cfr)} |")
    runs = complete(readings)
    lines += ["", f"Per kind over the {len(runs)} runs that read every kind:", ""]
    for kind in [kind for kind in POLICY_KINDS if runs and kind in next(iter(runs.values()))]:
        of_kind = [of_run[kind] for of_run in runs.values()]
        at_90 = sum(r.chosen_test_cfr >= 0.9 for r in of_kind)
        late = [r.late_test_min for r in of_kind if r.late_test_min is not None]
        lines.append(f"- {kind}: chosen test CFR mean {_percent(statistics.mean(r.chosen_test_cfr for r in of_kind))}, "
                     f"{at_90} of {len(of_kind)} at 90% or more"
                     + (f"; late curve's least test CFR {_percent(min(late))} at the least, "
                        f"{sum(value >= 0.8 for value in late)} of {len(late)} runs with none below 80%" if late else ""))
    lines += ["", *paired_lines(readings, bootstrap)]
    if runs:
        lines += ["", f"**Shipped by the rule: {shipped_kind(readings)}.**"]
    return lines


def write_readings(path: Path, readings: Sequence[KindReading]) -> Path:
    fields = list(KindReading.__dataclass_fields__)
    with path.open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=fields)
        writer.writeheader()
        writer.writerows({field: "" if getattr(r, field) is None else getattr(r, field) for field in fields}
                         for r in readings)
    return path


def report_on(folders: Sequence[Path], out: Path, bootstrap: Bootstrap | None = None, warn=print) -> list[Path]:
    readings = [reading for run in collect(folders, warn=warn) for reading in run_readings(run)]
    if not readings:
        raise ValueError("no exported run kept shadow policies in " + ", ".join(map(str, folders)))
    out.mkdir(parents=True, exist_ok=True)
    (out / PAGE).write_text("\n".join(report_lines(readings, bootstrap or Bootstrap())) + "\n")
    return [out / PAGE, write_readings(out / READINGS_CSV, readings)]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="deploy/studies/shadow_report.py", description=__doc__.splitlines()[0])
    parser.add_argument("folders", type=Path, nargs="+", help="folders of exported runs")
    parser.add_argument("--out", type=Path, required=True, help=f"where {PAGE} and {READINGS_CSV} go")
    args = parser.parse_args(argv)
    try:
        paths = report_on(args.folders, args.out, warn=lambda line: print(line, file=sys.stderr))
    except (ValueError, OSError, KeyError) as error:
        print(f"shadow_report: {error}", file=sys.stderr)
        return 1
    print((args.out / PAGE).read_text())
    print("wrote " + ", ".join(map(str, paths)), file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
