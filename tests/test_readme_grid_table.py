"""The README's table of the strategies past the knee is the committed report's: every row the report
gives for the grid's cells (buffer 1,000, the paper's learner options), in the README's columns, with the
same values, and the run count the README states. Static reading of two committed files."""

from __future__ import annotations

import re

from deploy.tools.readme_grid_table import (README, README_HEADER, REPORT, filled, report_run_count,
                                            report_strategy_rows, table_rows)


def readme_grid_table() -> list[dict[str, str]]:
    return table_rows(README.read_text(), README_HEADER)


def test_the_readme_grid_table_is_the_reports():
    readme, report = readme_grid_table(), report_strategy_rows(REPORT.read_text())
    assert [row["Strategy"] for row in readme] == list(report), "the README lists the report's strategies in order"
    for row in readme:
        expected = {column: report[row["Strategy"]][column] for column in row}
        assert row == expected, f"the README's {row['Strategy']} row differs from results/grid/grid.md"


def test_the_readme_states_the_reports_run_count():
    runs = report_run_count(REPORT.read_text())
    assert re.search(rf"\b{runs}\s+runs done", README.read_text())


def test_the_writer_fills_a_stale_readme_from_the_report():
    """deploy/tools/readme_grid_table.py: rows and count of an older report replaced by the committed one's."""
    readme, report = README.read_text(), REPORT.read_text()
    stale = re.sub(r"^(\| bmc \|.*)$", "| bmc | 9 | stale | stale | 1 | stale | 1% | 1% |", readme, count=1, flags=re.M)
    stale = re.sub(r"\d+(\s+)runs done", r"3\g<1>runs done", stale, count=1)
    assert stale != readme and filled(stale, report) == readme
    assert filled(readme, report) == readme
