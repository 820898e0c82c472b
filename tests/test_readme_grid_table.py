"""The README's table of the strategies past the knee is the committed report's: every row the report
gives for the grid's cells (buffer 1,000, the paper's learner options), in the README's columns, with the
same values, and the run count the README states. Static reading of two committed files."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
REPORT = ROOT / "results" / "grid" / "grid.md"


def cells(line: str) -> list[str]:
    return [cell.strip() for cell in line.strip("|").split("|")]


def table_rows(text: str, first_header: str) -> list[dict[str, str]]:
    """The rows of the first table whose header row starts with `first_header`, keyed by header."""
    lines = text.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith(f"| {first_header}"))
    header, rows = cells(lines[start]), []
    for line in lines[start + 2:]:
        if not line.startswith("|"):
            break
        rows.append(dict(zip(header, cells(line), strict=True)))
    return rows


def section(text: str, heading: str) -> str:
    return text.split(heading, 1)[1].split("\n## ", 1)[0]


def readme_grid_table() -> list[dict[str, str]]:
    return table_rows(README.read_text(), "Strategy | Seeds | Updates to drive,")


def report_strategy_rows() -> dict[str, dict[str, str]]:
    rows = table_rows(section(REPORT.read_text(), "## Per strategy"), "Strategy |")
    grid = [row for row in rows if row["Buffer"] == "1000" and row["Options"] == "paper"]
    return {row["Strategy"]: row for row in grid}


def test_the_readme_grid_table_is_the_reports():
    readme, report = readme_grid_table(), report_strategy_rows()
    assert [row["Strategy"] for row in readme] == list(report), "the README lists the report's strategies in order"
    for row in readme:
        expected = {column: report[row["Strategy"]][column] for column in row}
        assert row == expected, f"the README's {row['Strategy']} row differs from results/grid/grid.md"


def test_the_readme_states_the_reports_run_count():
    runs = int(re.search(r"^(\d+) runs\.", REPORT.read_text(), re.M).group(1))
    assert f"{runs} of\n21 runs done" in README.read_text() or f"{runs} of 21 runs done" in README.read_text()
