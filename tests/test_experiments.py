"""The comparison: figures from logs, the pooled tables, and the runner's resume decisions, on hand-made runs.

No training runs here: logs are written with the recorder's own writer, evaluations with
evaluate's own report writer, checkpoints with the learner's checkpoint writer.
"""

from __future__ import annotations

import csv
import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from common.analysis.figures import (RunCurves, plot_epsilon, plot_loss_differences, plot_reward_bins,
                                     plot_reward_curves, seed_band)
from common.analysis.intervals import Bootstrap
from common.analysis.stats import summarise_all
from common.analysis.tables import EPISODES_CSV, write_episodes_csv, write_evaluation
from common.config_values import load_config
from common.run_dir import log_segments
from common.keys import Keys
from common.wire.envelope import encode
from common.wire.messages import EpisodeRecord
from common.wire.metrics import LearnerStats
from wire_examples import example_learner_stats
from deploy.studies.comparison import (ComparisonError, EvaluatedRun, comparison_markdown, comparison_rows,
                               read_episodes_csv, write_comparison_csv)
from deploy.studies.performance_profile import plot_performance_profiles
from deploy.studies.run_results import greedy_headline
from replay.recorder.arrival import Arrival, peek
from replay.recorder.reader import LogError
from replay.recorder.run_curves import read_run_curves
from replay.recorder.writer import LogWriter
from tests.grid_runs import EDGES, episode, fake_evaluation

ROOT = Path(__file__).resolve().parents[1]
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


# --- logs written with the recorder's writer ---------------------------------------------------------------------

def write_log(path: Path, run: str, strategy: str, capacity: int, messages: list[tuple[str, object]]) -> None:
    """A log as the recorder writes it; messages are (key relative to the run, wire message)."""
    config = load_config("smoke", overrides={"run.name": run, "exploration.strategy": strategy,
                                             "replay.capacity": capacity})
    root = Keys(config.transport.namespace, run).root
    writer = LogWriter(path, config, views=None)
    for number, (key, message) in enumerate(messages, 1):
        data = encode(message)
        writer.write(Arrival(f"{root}/{key}", data, number * 1_000_000, None, number), peek(data))
    writer.close()


def record(length: int, episode_return: float, epsilon: float, off_greedy: int = -1) -> tuple[str, EpisodeRecord]:
    return "metrics/actor/0", EpisodeRecord(actor_id=0, episode_index=0, length=length, episode_return=episode_return,
                                            collided=True, start_set="train", start_index=0, epsilon=epsilon,
                                            weights_version=0, wall_time=0.1, time=1.0, off_greedy=off_greedy)


def learner_report(updates: int, loss_abs_diff: float) -> tuple[str, LearnerStats]:
    return "metrics/learner/0", example_learner_stats(updates=updates, loss=0.5, loss_abs_diff=loss_abs_diff)


def progress(updates: int) -> tuple[str, LearnerStats]:  # same type, other key: not a metrics report
    return "learner/progress", example_learner_stats(updates=updates, env_steps=5)


def test_the_curves_of_a_resumed_run_join_its_logs_in_recording_order(tmp_path):
    first, second = tmp_path / "traffic.mcap", tmp_path / "traffic-2.mcap"
    write_log(first, "bmc-b50-s0", "bmc", 50, [record(10, 5.0, 1.0), learner_report(0, math.nan), progress(3),
                                                record(20, 7.0, 0.4), learner_report(50, 0.2)])
    write_log(second, "bmc-b50-s0", "bmc", 50, [learner_report(100, 0.1), record(30, 9.0, 0.3)])
    assert log_segments(first) == [first, second]
    curves = read_run_curves(log_segments(first))
    assert (curves.label, curves.strategy, curves.capacity) == ("bmc-b50-s0", "bmc", 50)
    assert curves.episode_returns == [5.0, 7.0, 9.0]
    assert curves.episode_lengths == [10, 20, 30]
    assert curves.episode_epsilons == pytest.approx([1.0, 0.4, 0.3])
    assert curves.learner_updates == [50, 100]  # the NaN report and the progress message are left out
    assert curves.loss_abs_diffs == pytest.approx([0.2, 0.1])


def test_an_unfinished_log_is_a_log_error(tmp_path):
    path = tmp_path / "traffic.mcap"
    write_log(path, "r", "bmc", 50, [record(10, 5.0, 1.0)])
    path.write_bytes(path.read_bytes()[:-100])
    with pytest.raises(LogError, match="unfinished"):
        read_run_curves([path])
    with pytest.raises(LogError):
        read_run_curves([])


# --- figures -------------------------------------------------------------------------------------------------

def curves(label: str, strategy: str, capacity: int, episodes: int = 150) -> RunCurves:
    rng = np.random.default_rng(len(label))
    return RunCurves(label, strategy, capacity, episode_returns=list(rng.uniform(0, 20, episodes)),
                     episode_lengths=list(rng.integers(5, 40, episodes)),
                     episode_epsilons=list(np.linspace(1, 0.1, episodes)),
                     learner_updates=list(range(50, 1050, 50)), loss_abs_diffs=list(rng.uniform(0.01, 0.1, 20)))


def assert_png(path: Path) -> None:
    assert path.read_bytes()[:8] == PNG_MAGIC


@pytest.mark.parametrize("names", [
    ("bmc-b1000-s0", "softmax-b1000-s0", "constant-b2000-s0"),  # one run per strategy, two capacities
    ("bmc-b1000-s0", "bmc-b1000-s1", "softmax-b1000-s0"),  # two seeds of one strategy: a line and a band
])
def test_training_figures_are_written(tmp_path, names):
    runs = [curves(name, name.split("-")[0], int(name.split("-")[1][1:])) for name in names]
    for name, plot in (("reward.png", plot_reward_curves), ("epsilon.png", plot_epsilon),
                       ("loss.png", plot_loss_differences)):
        plot(runs, tmp_path / name)
        assert_png(tmp_path / name)


def test_a_seed_band_is_the_mean_and_range_of_the_runs_over_the_stretch_they_share():
    first = (np.array([0.0, 1.0, 2.0]), np.array([0.0, 2.0, 4.0]))
    second = (np.array([1.0, 3.0]), np.array([10.0, 30.0]))
    x, mean, low, high = seed_band([first, second], points=3)
    assert x.tolist() == [1.0, 1.5, 2.0]  # where both runs have data
    assert mean.tolist() == [6.0, 9.0, 12.0] and low.tolist() == [2.0, 3.0, 4.0] and high.tolist() == [10.0, 15.0, 20.0]
    x, mean, low, high = seed_band([first])
    assert x is first[0] and mean is first[1] and low is first[1] and high is first[1]
    with pytest.raises(ValueError, match="share no stretch"):
        seed_band([first, (np.array([5.0, 6.0]), np.array([1.0, 1.0]))])


def test_figures_refuse_what_they_cannot_draw(tmp_path):
    with pytest.raises(ValueError, match="epsilon-based"):
        plot_epsilon([curves("softmax-b1000-s0", "softmax", 1000)], tmp_path / "e.png")
    with pytest.raises(ValueError, match="no runs"):
        plot_reward_curves([], tmp_path / "r.png")
    with pytest.raises(ValueError, match="3 shares for 4 bins"):
        plot_reward_bins({"p": [("BMC", "bmc", (0.2, 0.3, 0.5))]}, ["a", "b", "c", "d"], tmp_path / "b.png", "t")
    assert not list(tmp_path.iterdir())


# --- evaluations pooled into the paper's tables --------------------------------------------------------------

def assert_same(got, expected):
    """Equal episodes, a NaN (a measure the episode lacks) equal to a NaN: numpy's assert_equal."""
    np.testing.assert_equal(dataclasses.astuple(got), dataclasses.astuple(expected))


def test_episodes_csv_reads_back_as_written(tmp_path):
    fake_evaluation(tmp_path, [100, 50], progress=True)
    episodes, edges = read_episodes_csv(tmp_path / EPISODES_CSV)
    assert edges == EDGES
    assert_same(episodes[0], episode("greedy", "train", 100, "cap", (0, 0, 0, 100), 0, 90.0, 4, 3))
    assert (episodes[1].end, episodes[1].progress_m, episodes[1].streets, episodes[1].junctions) == (
        "stalled", 45.0, 2, 1)
    assert math.isnan(episodes[2].progress_m)  # the random episodes did not report progress
    assert math.isnan(episodes[2].streets) and math.isnan(episodes[2].junctions)  # nor the places
    assert [e.policy for e in episodes] == ["greedy", "greedy", "random"] * 2


def test_an_episodes_csv_from_before_progress_and_coverage_reads_back_without_them(tmp_path):
    fake_evaluation(tmp_path, [100, 10], progress=True)
    lines = (tmp_path / EPISODES_CSV).read_text().splitlines()
    columns = {lines[0].split(",").index(name) for name in ("progress_m", "streets", "junctions", "end_x", "end_y",
                                                            "end_heading", "end_place", "hit")}
    old = "\n".join(",".join(cell for number, cell in enumerate(line.split(",")) if number not in columns)
                    for line in lines)
    (tmp_path / EPISODES_CSV).write_text(old + "\n")
    episodes, _ = read_episodes_csv(tmp_path / EPISODES_CSV)
    assert len(episodes) == 6
    assert all(math.isnan(e.progress_m) and math.isnan(e.streets) and math.isnan(e.junctions) for e in episodes)
    assert all(math.isnan(e.end_x) and math.isnan(e.end_heading) and e.hit == e.end_place == "" for e in episodes)


def test_an_episodes_end_pose_reads_back_as_written(tmp_path):
    crashed = dataclasses.replace(episode("greedy", "test", 53, "collision", (0, 0, 0, 53), 1),
                                  end_x=117.5, end_y=-0.75, end_heading=2.99, end_place="B1-C1",
                                  hit="parked car on B1-C1 45 m from B1, 0.9 m right of the centre-line")
    write_episodes_csv(tmp_path / EPISODES_CSV, [crashed], EDGES)
    (back,), _ = read_episodes_csv(tmp_path / EPISODES_CSV)
    assert_same(back, crashed)


def test_a_file_that_is_not_an_episodes_csv_is_a_comparison_error(tmp_path):
    (tmp_path / "bad.csv").write_text("policy,start_set\ngreedy,test\n")
    with pytest.raises(ComparisonError, match="bad.csv"):
        read_episodes_csv(tmp_path / "bad.csv")
    with pytest.raises(ComparisonError, match="cannot read"):
        read_episodes_csv(tmp_path / "missing.csv")


def test_seeds_are_pooled_and_the_random_row_comes_once_per_table(tmp_path):
    runs = [EvaluatedRun("softmax", 1000, fake_evaluation(tmp_path / "softmax-s0", [100, 100]), 0, 3500),
            EvaluatedRun("bmc", 1000, fake_evaluation(tmp_path / "bmc-s1", [100, 40], random_length=6), 1, 3580),
            EvaluatedRun("bmc", 1000, fake_evaluation(tmp_path / "bmc-s0", [100, 20]), 0, 3600),
            EvaluatedRun("bmc", 2000, fake_evaluation(tmp_path / "bmc-b2000", [30, 30]), 0, None)]
    rows, edges = comparison_rows(runs, Bootstrap(replicates=4000))
    assert edges == EDGES
    layout = [("bmc", None, 2), ("bmc", 0, 1), ("bmc", 1, 1), ("softmax", None, 1), ("softmax", 0, 1),
              ("random", None, 1)]
    small = [("bmc", None, 1), ("bmc", 0, 1), ("random", None, 1)]
    assert [(r.start_set, r.capacity, r.strategy, r.seed, r.runs) for r in rows] == [
        (start_set, capacity, *row) for start_set in ("train", "test")
        for capacity, table in ((1000, layout), (2000, small)) for row in table]
    bmc = rows[0]  # seeds 0 and 1: lengths 100, 20 and 100, 40 from starts 0 and 1
    assert (bmc.seeds, bmc.updates) == ((0, 1), (3600, 3580))  # in seed order
    s = bmc.summary
    assert (s.runs, s.episodes, s.mean_length, s.min_length, s.cfr, s.iqm_length) == (2, 4, 65.0, 20, 0.5, 70.0)
    assert s.std_length == pytest.approx(math.sqrt((35 ** 2 + 45 ** 2 + 35 ** 2 + 25 ** 2) / 4))
    assert s.reward_shares == (0.0, 0.0, 0.0, 1.0)
    # One trial per start, so a replicate only redraws the two runs: both seed 0 (mean 60), one of each (65)
    # or both seed 1 (70); each run reaches the cap once in two, so the CFR never moves.
    assert (s.intervals["mean_length"].low, s.intervals["mean_length"].high) == (60.0, 70.0)
    assert (s.intervals["cfr"].low, s.intervals["cfr"].high) == (0.5, 0.5)
    assert (rows[1].summary.mean_length, rows[2].summary.mean_length) == (60.0, 70.0)  # each seed alone
    assert rows[5].summary.mean_length == 4  # the first run's random episodes, not the second's (6)

    markdown = comparison_markdown(rows, edges)
    assert markdown.count("### ") == 4
    assert ("| BMC | 0, 1 | 3,600, 3,580 | 4 | 65.00 [60.00, 70.00] | 70.00 [60.00, 70.00] | 35.71 | 20 | "
            "50.00% [50.00, 50.00] | 50% / 0% / 0% | – | 0.500 [0.500, 0.500] | 100.00% |") in markdown
    assert "| Random policy | – | – | 1 | 4.00 [4.00, 4.00] |" in markdown
    assert "| BMC | 0 | 3,600 | 2 | 60.00 [60.00, 60.00] |" in markdown  # the per-run table
    assert markdown.count("Each run on its own") == 2  # the capacity-1000 tables; 2000 has one run a row
    assert "| BMC | 0 | ? | 2 | 30.00" in markdown  # a run whose updates are unknown

    write_comparison_csv(rows, edges, tmp_path / "results.csv")
    with (tmp_path / "results.csv").open() as handle:
        table = list(csv.DictReader(handle))
    assert len(table) == len(rows) and list(table[0])[-1] == "share_0.75_1"
    first = table[0]
    assert (first["strategy"], first["seed"], first["seeds"], first["updates"], first["runs"]) == (
        "bmc", "all", "0;1", "3600;3580", "2")
    assert (float(first["mean_length_low"]), float(first["mean_length_high"])) == (60.0, 70.0)
    assert [(row["seed"], row["updates"]) for row in table[1:3]] == [("0", "3600"), ("1", "3580")]


def test_the_privileged_driver_is_a_baseline_row_after_the_random_one(tmp_path):
    runs = [EvaluatedRun("bmc", 1000, fake_evaluation(tmp_path / "bmc-s0", [100, 20]), 0, 10),
            EvaluatedRun("softmax", 1000, fake_evaluation(tmp_path / "softmax-s0", [30], privileged_length=100), 0, 10),
            EvaluatedRun("vdbe", 1000, fake_evaluation(tmp_path / "vdbe-s0", [30], privileged_length=7), 0, 10)]
    rows, edges = comparison_rows(runs, Bootstrap(replicates=50))
    train = [row for row in rows if row.start_set == "train"]
    assert [row.strategy for row in train if row.pooled] == ["vdbe", "bmc", "softmax", "random", "privileged"]
    assert train[-1].summary.mean_length == 100  # from the first run that has it, not the later one (7)
    assert "| Privileged driver | – | – | 1 | 100.00" in comparison_markdown(rows, edges)


def test_a_runs_headline_gives_its_intervals(tmp_path):
    fake_evaluation(tmp_path, [100, 100])
    assert greedy_headline(tmp_path) == (
        "train: mean length 100.0 [100.0, 100.0], CFR 100.0% [100.0, 100.0]; "
        "test: mean length 100.0 [100.0, 100.0], CFR 100.0% [100.0, 100.0]")


def test_progress_and_stalls_reach_the_tables(tmp_path):
    runs = [EvaluatedRun("vdbe", 1000, fake_evaluation(tmp_path / "a", [100, 50], progress=True), 0, 10)]
    rows, edges = comparison_rows(runs, Bootstrap(replicates=200))
    s = rows[0].summary
    assert (s.stalled_share, s.cfr, s.mean_progress_m) == (0.5, 0.5, pytest.approx(67.5))
    assert (s.mean_streets, s.mean_junctions) == (3.0, 2.0)  # 4 and 2 streets, 3 and 1 junctions
    assert "| VDBE | 0 | 10 | 2 | 75.00" in comparison_markdown(rows, edges)
    assert "| 50.00% [50.00, 50.00] | 0% / 0% / 50% | 67.5 |" in comparison_markdown(rows, edges)


def test_the_performance_profile_is_drawn_from_the_pooled_rows(tmp_path):
    runs = [EvaluatedRun("bmc", 1000, fake_evaluation(tmp_path / "s0", [100, 20]), 0, 1),
            EvaluatedRun("bmc", 1000, fake_evaluation(tmp_path / "s1", [100, 40]), 1, 1)]
    rows, _ = comparison_rows(runs, Bootstrap(replicates=200))
    plot_performance_profiles(rows, tmp_path / "profile.png", Bootstrap(replicates=200))
    assert_png(tmp_path / "profile.png")
    with pytest.raises(ValueError, match="no pooled rows"):
        plot_performance_profiles([row for row in rows if not row.pooled], tmp_path / "none.png")


def test_evaluations_with_other_reward_bins_are_not_pooled(tmp_path):
    first = fake_evaluation(tmp_path / "a", [100])
    other = tmp_path / "b"
    episodes = [episode("greedy", "test", 10, "collision", (5, 5))]
    write_evaluation(other, episodes, summarise_all(episodes), [0.0, 0.5, 1.0], {}, 1, "")
    with pytest.raises(ComparisonError, match="reward bins"):
        comparison_rows([EvaluatedRun("bmc", 1000, first), EvaluatedRun("vdbe", 1000, other)])
    with pytest.raises(ComparisonError, match="no evaluated runs"):
        comparison_rows([])
