"""The evaluate command: statistics by hand, lockstep batching against one env at a time, end to end."""

import csv
import dataclasses
import io
import json
import math
import os

import numpy as np
import pytest
import torch

from actor.evaluation.command import build_parser, main
from actor.evaluation import EvaluationError
from actor.evaluation.episodes import (EpisodeJob, GreedyPolicy, PrivilegedPolicy, RandomPolicy, coverage_of,
                                       end_reason, episode_jobs, evaluation_env_config, progress_of, run_lockstep,
                                       trial_seed)
from actor.evaluation.sources import check_weights, checkpoint_config, live_source
from actor.evaluation.status import EvaluationStatus, evaluation_line
from actor.evaluation.workers import run_jobs, worker_layout
from actor.sim import make_env
from common.analysis.stats import (END_REASONS, EvaluationEpisode, digest_of_actions, reward_bin_counts, summarise,
                                   summarise_all)
from common.analysis.tables import bin_labels, failures_by_site, failures_by_start, markdown_table
from common.checkpoint import save_checkpoint
from common.config import TransportConfig
from common.sim_config import EvaluationConfig
from common.config_values import load_config, to_dict
from common.transport import open_session, serve
from common.keys import Keys
from common.wire.messages import Weights
from learner.update import DoubleQLearner
from tests.processes import loopback_endpoint

EDGES = [0.0, 0.25, 0.5, 0.75, 1.0]


def episode(length, end, episode_return, bins, start_index=0, digest="a", policy="greedy", start_set="test",
            progress_m=math.nan, streets=math.nan, junctions=math.nan):
    return EvaluationEpisode(policy=policy, start_set=start_set, start_index=start_index, trial=0, seed=0,
                             length=length, end=end, episode_return=episode_return, reward_bin_counts=bins,
                             actions_digest=digest, progress_m=progress_m, streets=streets, junctions=junctions)


# --- statistics ----------------------------------------------------------------------------------

def test_reward_bins_are_half_open_except_the_last():
    rewards = [0.0, 0.1, 0.25, 0.5, 0.74, 0.75, 0.99, 1.0]
    assert reward_bin_counts(rewards, EDGES) == (2, 1, 2, 3)
    assert reward_bin_counts([], EDGES) == (0, 0, 0, 0)
    assert bin_labels(EDGES) == ["[0, 0.25)", "[0.25, 0.5)", "[0.5, 0.75)", "[0.75, 1]"]


@pytest.mark.parametrize("reward", [-0.01, 1.01])
def test_a_reward_outside_the_bins_is_an_error(reward):
    with pytest.raises(ValueError, match="outside the bins"):
        reward_bin_counts([0.5, reward], EDGES)


def test_summary_of_hand_made_episodes():
    episodes = [
        episode(2, "collision", 1.0, (1, 0, 0, 1), start_index=0, digest="a", progress_m=2.0, streets=1, junctions=0),
        episode(4, "offroad", 2.0, (0, 2, 2, 0), start_index=0, digest="a", progress_m=3.5, streets=1, junctions=0),
        episode(6, "stalled", 3.0, (0, 0, 3, 3), start_index=1, digest="b", progress_m=0.5, streets=2, junctions=1),
        episode(8, "cap", 4.0, (2, 2, 2, 2), start_index=1, digest="c", progress_m=8.0, streets=4, junctions=4),
    ]
    row = summarise(episodes)
    assert (row.policy, row.start_set, row.runs, row.episodes) == ("greedy", "test", 1, 4)
    assert row.mean_length == 5.0
    assert row.iqm_length == 5.0  # the middle two of 2, 4, 6, 8
    assert row.std_length == pytest.approx(math.sqrt((9 + 1 + 1 + 9) / 4))  # population std
    assert (row.min_length, row.max_length) == (2, 8)
    assert row.cfr == 0.25  # only the one that reached the cap: stalling is no success
    assert (row.collision_share, row.offroad_share, row.stalled_share) == (0.25, 0.25, 0.25)
    assert row.mean_progress_m == pytest.approx(14.0 / 4)
    assert (row.mean_streets, row.mean_junctions) == (8 / 4, 5 / 4)
    # the row's mean is that of its two starts' means: start 0's two trials always give 1 street and 0
    # junctions; start 1's draw 2 of its trials of 2 and 4 streets (1 and 4 junctions) again: its mean is 2,
    # 3 or 4 streets (1, 2.5 or 4 junctions), with chances 1/4, 1/2, 1/4
    streets, junctions = row.intervals["streets"], row.intervals["junctions"]
    assert (streets.low, streets.high) == (1.5, 2.5) and (junctions.low, junctions.high) == (0.5, 2.0)
    assert row.mean_reward_per_step == pytest.approx(10.0 / 20)  # pooled over the 20 steps
    assert row.reward_shares == pytest.approx((3 / 20, 4 / 20, 7 / 20, 6 / 20))
    assert row.distinct_per_start == 1.5  # start 0: one trajectory, start 1: two
    cfr = row.intervals["cfr"]  # per start one of two trials resampled twice: CFR 0 .. 1/2
    assert (cfr.low, cfr.high) == (0.0, 0.5)
    length = row.intervals["mean_length"]
    assert 2.0 <= length.low < 5.0 < length.high <= 8.0


def test_without_progress_the_row_says_so():
    row = summarise([episode(3, "cap", 3.0, (0, 0, 0, 3)), episode(5, "cap", 5.0, (0, 0, 0, 5))])
    assert math.isnan(row.mean_progress_m) and math.isnan(row.intervals["progress_m"].low)
    assert math.isnan(row.mean_streets) and math.isnan(row.intervals["junctions"].low)
    assert "| – | – | – |" in markdown_table([row], EDGES)  # progress, streets, junctions


def test_the_failures_are_told_start_by_start_with_the_steps_they_came_at():
    bins = (0, 0, 0, 1)
    episodes = [episode(2000, "cap", 1.0, bins, start_set="train"), episode(49, "collision", 1.0, bins, start_set="train"),
                episode(52, "collision", 1.0, bins, start_set="train"),
                episode(100, "offroad", 1.0, bins, start_index=3), episode(2000, "cap", 1.0, bins, start_index=3),
                episode(2000, "cap", 1.0, bins, start_index=4),  # no failure: no row
                episode(7, "stalled", 1.0, bins, start_index=4, policy="random")]  # another policy's
    assert failures_by_start(episodes)[2:] == [
        "| Set | Start | Collision-free | Collision / off-road / stalled | Failed at step: median (range) |",
        "|---|---:|---:|---:|---:|",
        "| test | 3 | 1/2 | 0 / 1 / 0 | 100 (100–100) |",
        "| train | 0 | 1/3 | 2 / 0 / 0 | 50.5 (49–52) |"]
    assert failures_by_start(episodes[:1]) == ["Every greedy episode reached the cap."]
    assert failures_by_start(episodes, policy="privileged") == []


def test_the_failures_are_told_by_what_they_hit_or_where_they_ended():
    deep = "parked car on B1-C1 45 m from B1, 0.9 m right of the centre-line"

    def failed(length, end, start_set, start_index, hit="", end_place="B1-C1"):
        return dataclasses.replace(episode(length, end, 1.0, (0, 0, 0, 1), start_index, start_set=start_set),
                                   hit=hit, end_place=end_place)

    episodes = [failed(53, "collision", "test", 1, deep), failed(750, "collision", "test", 9, deep),
                failed(52, "collision", "train", 4, deep), failed(300, "offroad", "test", 2, end_place="C1"),
                failed(400, "collision", "test", 2, "a tree"), episode(2000, "cap", 1.0, (0, 0, 0, 1))]
    assert failures_by_site(episodes)[2:] == [
        "| Where | Episodes (train / test) | Starts | Failed at step: median (range) |", "|---|---:|---|---:|",
        f"| {deep} | 3 (1 / 2) | train 4; test 1, 9 | 53 (52–750) |",
        "| a tree | 1 (0 / 1) | test 2 | 400 (400–400) |",
        "| offroad on C1 | 1 (0 / 1) | test 2 | 300 (300–300) |"]
    assert failures_by_site(episodes[-1:]) == []  # nothing failed
    assert failures_by_site([*episodes, episode(9, "collision", 1.0, (0, 0, 0, 1))]) == []  # one without its site


def test_summaries_group_by_policy_and_set_and_refuse_mixed_or_empty_groups():
    episodes = [episode(3, "cap", 3.0, (0, 0, 0, 3), policy="greedy", start_set="train"),
                episode(1, "collision", 0.0, (1, 0, 0, 0), policy="random", start_set="train"),
                episode(5, "cap", 5.0, (0, 0, 0, 5), policy="greedy", start_set="train")]
    rows = summarise_all(episodes)
    assert [(row.policy, row.episodes, row.mean_length) for row in rows] == [("greedy", 2, 4.0), ("random", 1, 1.0)]
    with pytest.raises(ValueError, match="one policy"):
        summarise(episodes)
    with pytest.raises(ValueError, match="empty"):
        summarise([])
    table = markdown_table(rows, EDGES).splitlines()
    assert len(table) == 4
    assert table[0].startswith("| Policy | Set | Episodes | Mean length [95% CI] | IQM [95% CI] | Std | Min | "
                               "CFR [95% CI] | Collision | Off-road | Stalled | Progress m [95% CI] |")
    # lengths 3 and 5, both at the cap: a replicate draws 2 of the 2, so the mean is 3, 4 or 5
    assert table[2].startswith("| greedy | train | 2 | 4.00 [3.00, 5.00] | 4.00 [3.00, 5.00] | 1.00 | 3 | "
                               "100.00% [100.00, 100.00] | 0.00% | 0.00% | 0.00% |")


def test_end_reasons():
    # the simulator's own reason, when it gives one
    assert end_reason({"end": "stalled", "collision": False, "offroad": False}, True, 3, 30) == "stalled"
    assert end_reason({"end": "offroad", "collision": False, "offroad": True}, True, 3, 30) == "offroad"
    assert end_reason({"end": "cap", "collision": False, "offroad": False}, False, 30, 30) == "cap"
    assert end_reason({"end": None, "collision": False, "offroad": False}, False, 29, 30) is None
    # a simulator without info["end"]: its flags, a collision winning
    assert end_reason({"collision": True, "offroad": True}, True, 3, 30) == "collision"
    assert end_reason({"collision": False, "offroad": True}, True, 3, 30) == "offroad"
    assert end_reason({"collision": False, "offroad": False}, False, 29, 30) is None
    assert end_reason({"collision": False, "offroad": False}, False, 30, 30) == "cap"
    with pytest.raises(ValueError, match="does not know"):
        end_reason({"collision": False, "offroad": False}, True, 3, 30)
    with pytest.raises(ValueError, match="does not know"):
        end_reason({"end": "bored"}, True, 3, 30)


def test_progress_is_the_last_steps_and_nan_when_not_reported():
    assert progress_of({"progress_m": 12.5}) == 12.5
    assert math.isnan(progress_of({"collision": False}))


def test_coverage_counts_the_places_and_is_nan_when_not_reported():
    assert coverage_of(("A1-B1", "B1", "B1-B2", "B2", "B2-C2")) == (3, 2)
    assert all(math.isnan(count) for count in coverage_of(None))


def test_evaluation_line():
    assert evaluation_line(30, 120, 600, 10.0) == ("evaluate: 30/120 episodes (25.0%), 3.00 episodes/s, "
                                                   "60 steps/s, elapsed 0:10, ETA 0:30")
    assert evaluation_line(0, 120, 0, 0.0).endswith("ETA ?")


class _Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


@pytest.mark.parametrize("stream, lines_by_second", [(io.StringIO(), {1: 0, 29: 0, 30: 1, 45: 1, 60: 2}),
                                                     (_Terminal(), {1: 1, 29: 29, 30: 30})])
def test_the_status_line_is_written_each_second_on_a_terminal_and_each_log_period_into_a_log(stream, lines_by_second):
    now = [0.0]
    status = EvaluationStatus(10, 1.0, stream=stream, clock=lambda: now[0], log_period_s=30.0)
    for second in range(1, max(lines_by_second) + 1):
        now[0] = float(second)
        status.tick()
        if second in lines_by_second:
            written = stream.getvalue().count("\r" if isinstance(stream, _Terminal) else "\n")
            assert written == lines_by_second[second], second


def test_jobs_cover_every_start_and_trial_with_distinct_seeds():
    jobs = episode_jobs(["greedy", "random"], ["train", "test"], 3, root_seed=0)
    assert len(jobs) == 2 * 2 * 10 * 3
    greedy = [job for job in jobs if job.policy == "greedy"]
    assert len({job.seed for job in greedy}) == len(greedy)
    assert [job.seed for job in greedy] == [job.seed for job in jobs if job.policy == "random"]


# --- lockstep batching ---------------------------------------------------------------------------

@pytest.fixture(scope="module")
def small_config():
    return load_config("smoke", overrides={"evaluation.max_steps": 30})


@pytest.fixture(scope="module")
def network(small_config):
    torch.set_num_threads(1)
    return DoubleQLearner(small_config.network, small_config.learner).online.eval()


def one_env_at_a_time(config, network, job):
    """The reference: a fresh zero state, one frame per forward pass, as the actor steps."""
    env = make_env(evaluation_env_config(config))
    observation, _ = env.reset(seed=job.seed, options={"start_set": job.start_set, "start_index": job.start_index})
    state = network.initial_state(1)
    actions, rewards = [], []
    with torch.no_grad():
        while True:
            q_values, state = network(torch.from_numpy(observation)[None, None], state)
            actions.append(int(q_values[0, 0].argmax()))
            observation, reward, terminated, _, info = env.step(actions[-1])
            rewards.append(reward)
            end = end_reason(info, terminated, len(actions), config.evaluation.max_steps)
            if end is not None:
                env.close()
                return len(actions), end, digest_of_actions(actions), sum(rewards)


def lockstep(config, network, jobs, n_envs):
    envs = [make_env(evaluation_env_config(config)) for _ in range(n_envs)]
    policies = {"greedy": GreedyPolicy(network, n_envs), "random": RandomPolicy(config.network.n_actions, n_envs)}
    episodes = []
    run_lockstep(jobs, envs, policies, config.evaluation.max_steps, EDGES, episodes.append)
    return {(e.policy, e.start_set, e.start_index): e for e in episodes}


def test_batched_lockstep_gives_the_episodes_of_one_env_at_a_time(small_config, network):
    jobs = episode_jobs(["greedy"], ["test"], 1, root_seed=0) + episode_jobs(["random"], ["train"], 1, root_seed=0)[:4]
    batched = lockstep(small_config, network, jobs, n_envs=3)
    single = lockstep(small_config, network, jobs, n_envs=1)
    assert batched == single
    assert lockstep(small_config, network, jobs, n_envs=len(jobs)) == single  # all side by side, as 64 envs run
    lengths = set()
    for job in jobs[:10]:
        got = batched[("greedy", job.start_set, job.start_index)]
        assert (got.length, got.end, got.actions_digest) == one_env_at_a_time(small_config, network, job)[:3]
        assert got.episode_return == pytest.approx(one_env_at_a_time(small_config, network, job)[3])
        lengths.add(got.length)
    assert len(lengths) > 1  # episodes of different lengths: slots were refilled mid-batch


def test_an_episode_record_counts_the_streets_and_junctions_it_visited():
    config = load_config("smoke", overrides={"evaluation.max_steps": 80})
    env_config = evaluation_env_config(config)
    # Test start 5 is on D2-D3 15 m from D2, 55 m before the corner D3, where the only way on is to C3;
    # test start 0 is on B1-C1 12 m from B1, 58 m before C1, where turning right is to C2. The corner
    # curves begin 12 m before the junctions and are 19 m long, so 80 steps of 1 m end 15 m into C3-D3 /
    # C1-C2: two streets and the junction between them.
    jobs = [EpisodeJob("privileged", "test", 5, 0, trial_seed(0, "test", 5, 0)),
            EpisodeJob("right-turns", "test", 0, 0, trial_seed(0, "test", 0, 0))]
    policies = {"privileged": PrivilegedPolicy(env_config, 1),
                "right-turns": PrivilegedPolicy(env_config, 1, turns="right")}
    episodes = []
    run_lockstep(jobs, [make_env(env_config)], policies, 80, EDGES, episodes.append)
    assert [(e.policy, e.length, e.end, e.streets, e.junctions) for e in episodes] == [
        ("privileged", 80, "cap", 2, 1), ("right-turns", 80, "cap", 2, 1)]
    # where each ended: 43 m to the curve, 19 m round it, which ends 12 m past D3 (215, 140), and 18 m on: 30 m
    # west of D3; 46 m, 19 m round, then 15 m on: 27 m south of C1 (145, 0)
    (west, south) = episodes
    assert abs(west.end_x - 185) < 3 and abs(west.end_y - 140) < 2.6 and abs(abs(west.end_heading) - math.pi) < 0.3
    assert abs(south.end_x - 145) < 2.6 and abs(south.end_y - 27) < 3 and abs(south.end_heading - math.pi / 2) < 0.3


def test_the_lockstep_stops_between_two_steps_once_it_is_not_wanted():
    """A worker whose parent is gone stops at once, not after its simulators' episodes reach the cap."""
    env_config = evaluation_env_config(load_config("smoke", overrides={"evaluation.max_steps": 80}))
    job = EpisodeJob("privileged", "test", 5, 0, trial_seed(0, "test", 5, 0))  # drives the 80 steps (above)
    asked, episodes = [], []

    def wanted():
        asked.append(True)
        return len(asked) <= 10

    run_lockstep([job], [make_env(env_config)], {"privileged": PrivilegedPolicy(env_config, 1)}, 80, EDGES,
                 episodes.append, wanted)
    assert episodes == [] and len(asked) == 11  # 10 steps, then asked once more, and stopped
    run_lockstep([job], [make_env(env_config)], {"privileged": PrivilegedPolicy(env_config, 1)}, 80, EDGES,
                 episodes.append)
    assert [(episode.length, episode.end) for episode in episodes] == [(80, "cap")]


def test_starting_an_episode_zeroes_only_its_slot_state(network):
    policy = GreedyPolicy(network, 3)
    policy.hidden.fill_(1.0)
    policy.cell.fill_(1.0)
    policy.begin(1, EpisodeJob("greedy", "test", 0, 0, 0), (0.0, 0.0, 0.0))
    assert policy.hidden[:, 1].abs().sum() == 0 and policy.cell[:, 1].abs().sum() == 0
    assert bool((policy.hidden[:, [0, 2]] == 1).all()) and bool((policy.cell[:, [0, 2]] == 1).all())


def test_a_worker_steps_no_more_simulators_than_its_share_of_the_jobs(monkeypatch):
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 1})
    evaluation = EvaluationConfig(workers=2, envs_per_worker=64)
    assert worker_layout(evaluation, 1200) == (2, 64, 1)  # a full evaluation: every simulator has work
    assert worker_layout(evaluation, 100) == (2, 50, 1)  # a curve's policy: half the queue each, not 64 and 36
    assert worker_layout(evaluation, 3) == (2, 2, 1)
    assert worker_layout(evaluation, 1) == (1, 1, 2)
    assert worker_layout(EvaluationConfig(workers=1, envs_per_worker=8, torch_threads=1), 50) == (1, 8, 1)


def test_a_failing_worker_is_an_evaluation_error(small_config):
    jobs = [EpisodeJob("greedy", "test", 0, 0, 0)]  # no weights, so the worker has no greedy policy
    with pytest.raises(EvaluationError, match="no 'greedy' policy"):
        run_jobs(small_config, None, jobs, EvaluationStatus(len(jobs), 0.2, stream=None))


# --- end to end ------------------------------------------------------------------------------------

def make_checkpoint(runs_dir):
    """A checkpoint in the layout learner/service.py writes, from a smoke-preset config."""
    config = load_config("smoke", overrides={"run.name": "tiny", "run.runs_dir": str(runs_dir)})
    learner = DoubleQLearner(config.network, config.learner)
    save_checkpoint(runs_dir / "tiny" / "checkpoints", {
        "learner": learner.state_dict(), "exploration": {}, "clock": {"env_steps": 0}, "config": to_dict(config)})
    return runs_dir / "tiny"


def read_csv(path):
    with path.open() as handle:
        return list(csv.DictReader(handle))


def test_evaluate_a_checkpoint_end_to_end(tmp_path, capsys):
    run_dir = make_checkpoint(tmp_path / "runs")
    # The checkpoint's smoke config gives 1 episode per start, 1 worker, 2 envs; the flag changes the cap.
    main(["--checkpoint", str(run_dir), "--evaluation.max_steps", "30"])
    out = run_dir / "evaluation"
    episodes = read_csv(out / "episodes.csv")
    assert len(episodes) == 2 * 2 * 10  # greedy and random, train and test, 10 starts, 1 trial
    assert {(row["policy"], row["start_set"]) for row in episodes} == {
        ("greedy", "train"), ("greedy", "test"), ("random", "train"), ("random", "test")}
    assert all(1 <= int(row["length"]) <= 30 for row in episodes)
    assert all(sum(int(row[key]) for key in row if key.startswith("steps_")) == int(row["length"]) for row in episodes)
    assert all(row["end"] in END_REASONS and (row["end"] == "cap") == (row["collision_free"] == "True")
               for row in episodes)
    progress = [float(row["progress_m"]) for row in episodes]  # NaN from a simulator that does not report it
    assert all(math.isnan(value) for value in progress) or all(value >= 0 for value in progress)
    # 30 steps of 1 m cannot pass two junctions (streets are 70 m or more): the start street, at most one
    # junction and the street beyond it
    assert all(int(row["streets"]) in (1, 2) and int(row["junctions"]) in (0, 1) for row in episodes)
    summary = read_csv(out / "summary.csv")
    assert [(row["policy"], row["start_set"], row["episodes"]) for row in summary] == [
        ("greedy", "train", "10"), ("greedy", "test", "10"), ("random", "train", "10"), ("random", "test", "10")]
    for row in summary:
        for statistic, value in (("mean_length", "mean_length"), ("cfr", "cfr"),
                                 ("reward_per_step", "mean_reward_per_step"), ("iqm_length", "iqm_length"),
                                 ("streets", "mean_streets"), ("junctions", "mean_junctions")):
            low, point, high = (float(row[key]) for key in (f"{statistic}_low", value, f"{statistic}_high"))
            assert low - 1e-9 <= point <= high + 1e-9  # equal up to rounding where every draw agrees
    assert json.loads((out / "facts.json").read_text())["updates"] == "0"
    markdown = (out / "summary.md").read_text()
    assert sum(line.startswith(("| greedy |", "| random |")) for line in markdown.splitlines()) == 4
    assert "Where the greedy policy failed" in markdown or "Every greedy episode reached the cap." in markdown
    assert "max_steps = 30" in (out / "config.toml").read_text()
    assert "| Policy | Set |" in capsys.readouterr().out


def test_checkpoint_config_then_file_then_flags(tmp_path):
    saved = to_dict(load_config("smoke", overrides={"evaluation.workers": 3}))
    toml = tmp_path / "eval.toml"
    toml.write_text("[evaluation]\nworkers = 2\nmax_steps = 100\n")
    args = build_parser().parse_args(["--checkpoint", "x", "--config", str(toml), "--evaluation.max_steps", "30"])
    config = checkpoint_config(saved, args)
    assert config.evaluation.episodes_per_start == 1  # the checkpoint's (smoke), not the paper preset's 30
    assert config.evaluation.workers == 2  # the file over the checkpoint
    assert config.evaluation.max_steps == 30  # the flag over the file


def test_a_missing_checkpoint_is_a_clear_error(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["--checkpoint", str(tmp_path / "nothing")])
    assert exit_info.value.code == 1
    assert "evaluate: error: no checkpoint at" in capsys.readouterr().err


# --- live weights ------------------------------------------------------------------------------------

def live_config(endpoint, timeout_s):
    return load_config("smoke", overrides={"run.name": "live", "transport.connect": [endpoint],
                                           "evaluation.live_timeout_s": timeout_s})


def test_live_weights_are_the_learners_latest(small_config):
    endpoint = loopback_endpoint()
    config = live_config(endpoint, 10.0)
    served = Weights(version=7, tensors={"only": np.arange(3, dtype=np.float32)})
    with open_session(TransportConfig(listen=[endpoint])) as learner:
        queryable = serve(learner, Keys(config.transport.namespace, "live").weights_latest, lambda request: served)
        source = live_source(config)
        queryable.undeclare()
    assert source.facts["weights version"] == "7"
    assert source.weights["only"].tolist() == [0.0, 1.0, 2.0]
    with pytest.raises(EvaluationError, match="do not fit the configured network"):
        check_weights(config, source.weights)


def test_no_live_learner_is_a_clear_error():
    with pytest.raises(EvaluationError, match="no learner answered"):
        live_source(live_config(loopback_endpoint(), 0.5))
