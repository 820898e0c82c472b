"""The figures' shared finish: compact tick labels for counts in the thousands."""

from __future__ import annotations

import pytest

from common.analysis.plotting import finish_figure, pyplot, tick_text


@pytest.mark.parametrize("largest, value, text", [
    (150_000, 40_000, "40k"), (150_000, 2_500, "2.5k"), (150_000, 0, "0"),
    (1_000_000, 250_000, "0.25M"), (20_000_000, 1_500_000, "1.5M"),
    (9_999, 5_000, "5000"), (2.5, 0.5, "0.5"), (10_000, 10_000, "10k"),
])
def test_tick_text_scales_by_the_axis_end(largest, value, text):
    assert tick_text(largest)(value) == text


def test_finish_figure_gives_env_step_axes_compact_labels_and_leaves_log_axes(tmp_path):
    plt = pyplot()
    figure, (steps, log) = plt.subplots(1, 2)
    steps.plot([0, 150_000], [0, 1])
    log.plot([1, 100_000], [1, 2])
    log.set_xscale("log")
    before = log.xaxis.get_major_formatter()
    finish_figure(plt, figure, [steps, log], tmp_path / "figure.png", "title")
    assert steps.xaxis.get_major_formatter()(80_000) == "80k"
    assert log.xaxis.get_major_formatter() is before
    assert (tmp_path / "figure.png").stat().st_size > 0
