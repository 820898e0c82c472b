"""The comparison: figures from logs, the pooled tables, and the runner's resume decisions, on hand-made runs.

No training runs here: logs are written with the recorder's own writer, evaluations with
evaluate's own report writer, checkpoints with the learner's checkpoint writer.
"""

from __future__ import annotations

import csv
import importlib.util
import math
import sys
from pathlib import Path

import numpy as np
import pytest

from common.analysis.figures import (RunCurves, plot_epsilon, plot_loss_differences, plot_reward_bins,
                                     plot_reward_curves, seed_band)
from common.analysis.intervals import Bootstrap
from common.analysis.stats import EvaluationEpisode, summarise_all
from common.analysis.tables import EPISODES_CSV, write_evaluation
from common.checkpoint import save_checkpoint
from common.config_values import load_config, to_toml
from common.run_dir import log_segments
from common.transport import Keys
from common.wire.envelope import encode
from common.wire.messages import EpisodeRecord, Stats
from deploy.comparison import (ComparisonError, EvaluatedRun, comparison_markdown, comparison_rows,
                               read_episodes_csv, write_comparison_csv)
from deploy.performance_profile import plot_performance_profiles
from replay.log.arrival import Arrival, peek
from replay.log.reader import LogError
from replay.log.run_curves import read_run_curves
from replay.log.writer import LogWriter

ROOT = Path(__file__).resolve().parents[1]
EDGES = [0.0, 0.25, 0.5, 0.75, 1.0]
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def load_runner():
    """deploy/experiments.py is a script run by path, as deploy/stack.py; load it as a module."""
    spec = importlib.util.spec_from_file_location("experiments", ROOT / "deploy" / "experiments.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


experiments = load_runner()


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


def record(length: int, episode_return: float, epsilon: float) -> tuple[str, EpisodeRecord]:
    return "metrics/actor/0", EpisodeRecord(actor_id=0, episode_index=0, length=length, episode_return=episode_return,
                                            collided=True, start_set="train", start_index=0, epsilon=epsilon,
                                            weights_version=0, wall_time=0.1, time=1.0)


def learner_report(updates: int, loss_abs_diff: float) -> tuple[str, Stats]:
    return "metrics/learner/0", Stats(source="learner", time=1.0,
                                      values={"updates": updates, "loss": 0.5, "loss_abs_diff": loss_abs_diff})


def progress(updates: int) -> tuple[str, Stats]:  # same source, other key: not a metrics report
    return "learner/progress", Stats(source="learner", time=1.0, values={"updates": updates, "env_steps": 5})


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

def episode(policy: str, start_set: str, length: int, end: str, bins: tuple[int, ...], start_index: int = 0,
            progress_m: float = math.nan, streets: float = math.nan, junctions: float = math.nan) -> EvaluationEpisode:
    return EvaluationEpisode(policy=policy, start_set=start_set, start_index=start_index, trial=0, seed=7,
                             length=length, end=end, episode_return=0.5 * length, reward_bin_counts=bins,
                             actions_digest=f"d{length}", progress_m=progress_m, streets=streets, junctions=junctions)


def fake_evaluation(directory: Path, greedy_lengths: list[int], random_length: int = 4, updates: int | None = None,
                    progress: bool = False, privileged_length: int | None = None) -> Path:
    """Greedy episodes of the given lengths on both sets (a length of 100 reaches the cap, 50 stalls), one
    random each (and one of the privileged driver if given); with progress, each greedy episode drove 0.9 m
    per step and visited a street per 25 steps (at least one) and a junction fewer."""
    episodes = []
    for start_set in ("train", "test"):
        for number, length in enumerate(greedy_lengths):
            end = {100: "cap", 50: "stalled"}.get(length, "collision")
            streets = max(1, length // 25)
            coverage = (streets, streets - 1) if progress else (math.nan, math.nan)
            episodes.append(episode("greedy", start_set, length, end, (0, 0, 0, length), number,
                                    0.9 * length if progress else math.nan, *coverage))
        episodes.append(episode("random", start_set, random_length, "offroad", (random_length, 0, 0, 0)))
        if privileged_length is not None:
            episodes.append(episode("privileged", start_set, privileged_length, "cap", (0, 0, 0, privileged_length)))
    facts = {} if updates is None else {"updates": str(updates)}
    write_evaluation(directory, episodes, summarise_all(episodes), EDGES, facts, 1, "")
    return directory


def test_episodes_csv_reads_back_as_written(tmp_path):
    fake_evaluation(tmp_path, [100, 50], progress=True)
    episodes, edges = read_episodes_csv(tmp_path / EPISODES_CSV)
    assert edges == EDGES
    assert episodes[0] == episode("greedy", "train", 100, "cap", (0, 0, 0, 100), 0, 90.0, 4, 3)
    assert (episodes[1].end, episodes[1].progress_m, episodes[1].streets, episodes[1].junctions) == (
        "stalled", 45.0, 2, 1)
    assert math.isnan(episodes[2].progress_m)  # the random episodes did not report progress
    assert math.isnan(episodes[2].streets) and math.isnan(episodes[2].junctions)  # nor the places
    assert [e.policy for e in episodes] == ["greedy", "greedy", "random"] * 2


def test_an_episodes_csv_from_before_progress_and_coverage_reads_back_without_them(tmp_path):
    fake_evaluation(tmp_path, [100, 10], progress=True)
    lines = (tmp_path / EPISODES_CSV).read_text().splitlines()
    columns = {lines[0].split(",").index(name) for name in ("progress_m", "streets", "junctions")}
    old = "\n".join(",".join(cell for number, cell in enumerate(line.split(",")) if number not in columns)
                    for line in lines)
    (tmp_path / EPISODES_CSV).write_text(old + "\n")
    episodes, _ = read_episodes_csv(tmp_path / EPISODES_CSV)
    assert len(episodes) == 6
    assert all(math.isnan(e.progress_m) and math.isnan(e.streets) and math.isnan(e.junctions) for e in episodes)


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
    assert experiments.evaluation_headline(tmp_path / "summary.csv") == (
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


# --- the runner ----------------------------------------------------------------------------------------------------

def options(tmp_path: Path, steps: int = 1000, extra: tuple[str, ...] = ()):
    return experiments.Options(tmp_path, steps, trials=3, actors=None, extra=extra, progress_s=30.0)


def make_run(run_dir: Path, env_steps: int | None = None, evaluated: bool = False, updates: int | None = None,
             strategy: str = "bmc", capacity: int = 50, seed: int = 0) -> Path:
    """A run folder as the stack and evaluate leave it: its config, a checkpoint with this clock, an evaluation."""
    run_dir.mkdir(parents=True, exist_ok=True)
    config = load_config("smoke", overrides={"run.name": run_dir.name, "exploration.strategy": strategy,
                                             "replay.capacity": capacity, "run.seed": seed})
    (run_dir / "config.toml").write_text(to_toml(config))
    if env_steps is not None:
        save_checkpoint(run_dir / "checkpoints", {"clock": {"env_steps": env_steps}, "learner": {"updates": 7}})
    if evaluated:
        fake_evaluation(run_dir / "evaluation", [100, 50], updates=updates)
    return run_dir


@pytest.mark.parametrize("env_steps, evaluated, expected", [
    (None, False, "train"),  # nothing yet, or an attempt stopped before its first checkpoint
    (400, False, "resume"),  # stopped before the budget
    (1000, False, "evaluate"),  # trained, not evaluated
    (1200, True, "done"),
    (400, True, "resume"),  # evaluated under a smaller budget: train on, evaluate again
    (None, True, "done"),  # an evaluation without its checkpoint is kept as it is
])
def test_what_a_run_folder_still_needs(tmp_path, env_steps, evaluated, expected):
    assert experiments.next_step(make_run(tmp_path / "run", env_steps, evaluated), 1000) == expected


def test_a_damaged_checkpoint_is_one_clear_error(tmp_path):
    run = make_run(tmp_path / "run")
    (run / "checkpoints").mkdir()
    (run / "checkpoints" / "latest.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(experiments.ExperimentError, match="cannot read the step count"):
        experiments.next_step(run, 1000)


def test_a_fresh_start_sets_the_abandoned_attempts_logs_aside(tmp_path):
    run = make_run(tmp_path / "run")
    assert experiments.set_aside_stale_files(run) is None
    for name in ("traffic.mcap", "traffic-2.mcap", "logs/learner.log", "config.toml"):
        (run / name).parent.mkdir(exist_ok=True)
        (run / name).write_text(name)
    moved = experiments.set_aside_stale_files(run)
    assert sorted(path.name for path in moved.iterdir()) == ["logs", "traffic-2.mcap", "traffic.mcap"]
    assert sorted(path.name for path in run.iterdir()) == ["abandoned", "config.toml"]


def test_the_grid_names_runs_and_passes_each_its_flags(tmp_path):
    specs = experiments.grid(["bmc", "softmax"], [1000, 2000], [0, 1])
    assert [spec.name for spec in specs[:3]] == ["bmc-b1000-s0", "softmax-b1000-s0", "bmc-b1000-s1"]
    assert len(specs) == 8
    opts = options(tmp_path, extra=("--preset", "local", "--env.max_steps", "500"))
    stack = experiments.stack_command(specs[0], opts, resume=True)
    assert stack[1].endswith("deploy/stack.py") and stack[-1] == "--resume"
    assert stack[2:6] == ["--preset", "local", "--env.max_steps", "500"]
    flags = dict(zip(stack[6:-1:2], stack[7:-1:2]))
    assert flags == {"--run.name": "bmc-b1000-s0", "--run.runs_dir": str(tmp_path), "--run.seed": "0",
                     "--exploration.strategy": "bmc", "--replay.capacity": "1000", "--learner.total_env_steps": "1000"}
    evaluate = experiments.evaluate_command(specs[0], opts)
    assert evaluate[1:7] == ["-m", "actor.evaluate", "--checkpoint", str(tmp_path / "bmc-b1000-s0"),
                             "--out", str(tmp_path / "bmc-b1000-s0" / "evaluation")]
    assert evaluate[-2:] == ["--evaluation.episodes_per_start", "3"] and "--privileged" not in evaluate
    assert "--privileged" in experiments.evaluate_command(specs[0], opts, privileged=True)


def test_runs_at_once_share_the_cores_between_their_learners_unless_told():
    assert experiments.learner_threads_flags([], parallel=1, cores=2) == []
    assert experiments.learner_threads_flags([], parallel=2, cores=2) == ["--learner.torch_threads", "1"]
    assert experiments.learner_threads_flags([], parallel=2, cores=8) == ["--learner.torch_threads", "4"]
    assert experiments.learner_threads_flags([], parallel=3, cores=2) == ["--learner.torch_threads", "1"]
    for given in (["--learner.torch_threads", "2"], ["--learner.torch_threads=2"]):
        assert experiments.learner_threads_flags(given, parallel=2, cores=2) == []


@pytest.mark.parametrize("extra, message", [
    (("--replay.capacity", "5"), "set by the grid"),
    (("--run.seed=4",), "set by the grid"),
    (("--learner.lr", "oops"), "learner.lr: expected a number"),
])
def test_config_flags_are_checked_before_anything_runs(tmp_path, extra, message):
    with pytest.raises(experiments.ExperimentError, match=message):
        experiments.check_config_flags(experiments.grid(["bmc"], [50], [0]), options(tmp_path, extra=extra))


def test_the_results_of_finished_runs_are_written(tmp_path):
    specs = experiments.grid(["bmc", "softmax"], [50], [0])
    opts = options(tmp_path)
    for spec, strategy in zip(specs, ("bmc", "softmax")):
        run = make_run(tmp_path / spec.name, 1000, evaluated=True, updates=120, strategy=strategy)
        write_log(run / "traffic.mcap", spec.name, strategy, 50,
                  [record(10, 5.0, 1.0), learner_report(50, 0.2), record(12, 6.0, 0.5), learner_report(100, 0.1)])
    paths = experiments.write_results(specs, opts, {"budget": "1,000"})
    assert sorted(path.name for path in paths) == ["differences.csv", "epsilon.png", "loss_differences.png",
                                                  "performance_profile.png", "results.csv", "results.md",
                                                  "reward_bins.png", "reward_curves.png"]
    for path in paths:
        if path.suffix == ".png":
            assert_png(path)
    markdown = (tmp_path / "results" / "results.md").read_text()
    assert markdown.count("| BMC | 0 | 120 | 2 |") == 2 and "- budget: 1,000" in markdown
    assert "95% percentile intervals of 2000 bootstrap replicates" in markdown
    # per set: bmc pooled and its seed, softmax pooled and its seed, random
    assert len((tmp_path / "results" / "results.csv").read_text().splitlines()) == 1 + 2 * 5
    exported = tmp_path / "results" / "runs"  # the tables were built from the exported runs
    assert sorted(path.name for path in exported.iterdir()) == ["bmc-b50-s0", "softmax-b50-s0"]
