"""The README's table of the strategies past the knee, filled from the committed report (results/grid/grid.md).

The README keeps its own columns (fewer than the report's); each row takes those columns' values from the
report's "Per strategy" row of the same strategy (the grid's cells: buffer 1,000, the paper's learner options),
and the README's "N runs done" takes the report's run count (21 in the grid, more as seeds are added).
tests/test_readme_grid_table.py fails when the README no longer matches the report.

    .venv/bin/python deploy/tools/readme_grid_table.py            # print the README's table as it should read
    .venv/bin/python deploy/tools/readme_grid_table.py --write    # replace the table and the count in README.md
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
README = ROOT / "README.md"
REPORT = ROOT / "results" / "grid" / "grid.md"
README_HEADER = "Strategy | Seeds | Updates to drive,"  # how the README's table's header row starts
RUN_COUNT = re.compile(r"(\d+)(\s+)runs done")


def cells(line: str) -> list[str]:
    return [cell.strip() for cell in line.strip().strip("|").split("|")]


def table_span(lines: list[str], first_header: str) -> tuple[int, int]:
    """The line range [start, end) of the first table whose header row starts with `first_header`."""
    start = next(i for i, line in enumerate(lines) if line.startswith(f"| {first_header}"))
    end = start + 2
    while end < len(lines) and lines[end].startswith("|"):
        end += 1
    return start, end


def table_rows(text: str, first_header: str) -> list[dict[str, str]]:
    """The rows of the first table whose header row starts with `first_header`, keyed by header."""
    lines = text.splitlines()
    start, end = table_span(lines, first_header)
    header = cells(lines[start])
    return [dict(zip(header, cells(line), strict=True)) for line in lines[start + 2:end]]


def report_strategy_rows(report: str) -> dict[str, dict[str, str]]:
    """The report's "Per strategy" rows of the grid's cells, by strategy, in the report's order."""
    per_strategy = report.split("## Per strategy", 1)[1].split("\n## ", 1)[0]
    rows = table_rows(per_strategy, "Strategy |")
    return {row["Strategy"]: row for row in rows if row["Buffer"] == "1000" and row["Options"] == "paper"}


def report_run_count(report: str) -> int:
    return int(re.search(r"^(\d+) runs\.", report, re.M).group(1))


def filled(readme: str, report: str) -> str:
    """The README with its grid table's rows and its run count taken from the report."""
    lines = readme.splitlines()
    start, end = table_span(lines, README_HEADER)
    header = cells(lines[start])
    rows = [f"| {' | '.join(row[column] for column in header)} |" for row in report_strategy_rows(report).values()]
    text = "\n".join([*lines[:start + 2], *rows, *lines[end:]]) + ("\n" if readme.endswith("\n") else "")
    runs = report_run_count(report)
    return RUN_COUNT.sub(lambda match: f"{runs}{match.group(2)}runs done", text, count=1)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--write", action="store_true", help="replace the table and the run count in README.md")
    args = parser.parse_args()
    text = filled(README.read_text(), REPORT.read_text())
    if args.write:
        README.write_text(text)
        print(f"wrote {README.relative_to(ROOT)}")
    else:
        start, end = table_span(text.splitlines(), README_HEADER)
        print("\n".join(text.splitlines()[start:end]))


if __name__ == "__main__":
    main()
