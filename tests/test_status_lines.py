"""Status lines you can plan by: the stack's budget, percentage and ETA, its status file, the grid's runs done
and ETA, and an actor's held episodes counted once per period."""

import logging
import math
import time

import numpy as np
import pytest

import deploy.grid.experiments as experiments
import deploy.grid.grid_job as grid_job
from deploy.grid import run_progress
from actor.gate import HoldLog
from common.checkpoint import save_checkpoint
from common.config_values import load_config
from common.eta import Eta, clock_time
from common.run_dir import RunDir, RunStatus
from common.wire.envelope import decode, encode
from common.wire.messages import EpisodeRecord, ReplayStats
from wire_examples import example_learner_stats, example_rate, example_replay_stats
from deploy.launcher.stack import Stack, StackMonitor
from fake_clock import FakeClock
from learner.prefetch import Prefetcher
from learner.metrics import LearnerMetrics
from learner.service import LearnerService
from learner.update import UpdateResult



def test_the_eta_follows_the_rate_of_its_window():
    clock = FakeClock()
    eta = Eta(2000, window_s=10.0, clock=clock)
    assert eta.remaining_s() is None and eta.text() == "?"
    eta.update(0)
    clock.now = 10.0
    eta.update(100)  # 10 per second
    assert eta.remaining_s() == pytest.approx(190.0)
    for done in (350, 600, 850, 1100):  # then 50 per second, and the first samples leave the window
        clock.now += 5.0
        eta.update(done)
    assert eta.remaining_s() == pytest.approx(900 / 50)
    eta.update(2500)
    assert eta.remaining_s() == 0.0
    assert clock_time(59.6) == "1:00" and clock_time(3725) == "1:02:05"


def test_the_eta_is_unknown_while_the_count_stands_still():
    clock = FakeClock()
    eta = Eta(10, clock=clock)
    eta.update(3)
    clock.now = 5.0
    eta.update(3)
    assert eta.remaining_s() is None


def replay_stats(env_steps: int, start: float | None = None, unpaced: bool = False) -> ReplayStats:
    rate = example_rate(env_steps=env_steps, start_env_steps=start, batches_served=0, unpaced=unpaced)
    return example_replay_stats(rate)


def test_the_stacks_line_and_status_show_the_budget_its_share_and_the_eta():
    clock = FakeClock()
    monitor = StackMonitor(20_000, clock=clock)
    monitor.on_replay_stats(replay_stats(1_000, unpaced=True), "k")
    clock.now = 10.0
    monitor.on_replay_stats(replay_stats(2_000, unpaced=True), "k")  # 100 steps/s: 18,000 steps in 3 minutes
    monitor.on_metric(EpisodeRecord(actor_id=0, episode_index=0, length=5, episode_return=4.5, collided=True,
                                    start_set="train", start_index=0, epsilon=1.0, weights_version=0,
                                    wall_time=0.1, time=1.0), "d3rqn/r/metrics/actor/0")
    line = monitor.line(restarts=1)
    assert "env steps     2,000/20,000 ( 10.0%, ETA 3:00) |" in line and line.endswith("restarts 1")
    status = monitor.status("training", {"actor-0": 1}, {"learner": 7})
    assert (status.env_steps, status.total_env_steps, status.episodes, status.mean_return) == (2_000, 20_000, 1, 4.5)
    assert status.eta_s == pytest.approx(180.0) and status.pids == {"learner": 7}


def test_the_line_shows_the_temperature_beside_epsilon_since_softmax_explores_at_eps_1():
    monitor = StackMonitor(20_000, clock=FakeClock())
    assert "eps 1.000 uniform       |" in monitor.line()  # nothing heard yet: the random phase's uniform actions
    for values, shown in (({"epsilon": 1.0, "kappa": 0.1}, "eps 1.000 kappa     0.1 |"),
                          ({"epsilon": 0.05, "kappa": 0.0}, "eps 0.050 uniform       |")):
        monitor.on_metric(example_learner_stats(**values), "d3rqn/r/metrics/learner/0")
        assert shown in monitor.line()


def test_the_learners_metrics_carry_its_strategys_temperature_to_the_line(tmp_path):
    config = load_config("smoke", overrides={"exploration.strategy": "softmax", "run.runs_dir": str(tmp_path)})
    service = LearnerService(config)
    service.strategy.start()
    prefetcher = Prefetcher(lambda request: None, 4, 10, depth=1)
    try:
        stats = LearnerMetrics(service, prefetcher).report()
    finally:
        prefetcher.close()
    assert (stats.epsilon, stats.kappa) == (1.0, config.exploration.softmax.kappa)
    monitor = StackMonitor(clock=FakeClock())
    monitor.on_metric(decode(encode(stats)), "d3rqn/r/metrics/learner/0")
    assert f"eps 1.000 kappa {config.exploration.softmax.kappa:7.3g} |" in monitor.line()


def test_a_paced_runs_eta_follows_the_updates_it_still_owes_not_the_random_phase():
    clock = FakeClock()
    monitor = StackMonitor(20_000, clock=clock)

    def report(env_steps: int, start: float | None, updates: int) -> None:
        monitor.on_replay_stats(replay_stats(env_steps, start), "k")
        monitor.on_metric(example_learner_stats(updates=updates), "d3rqn/r/metrics/learner/0")

    report(5_000, None, 0)
    clock.now = 10.0
    report(10_000, None, 0)  # 500 random steps a second: no guide to the learner's pace
    assert "ETA ?" in monitor.line() and monitor.status("training", {}, {}).eta_s is None
    report(10_000, 10_000.0, 0)  # updates start: 2,500 owed to reach 20,000 steps
    clock.now = 60.0
    report(12_000, 10_000.0, 100)  # 2 updates a second
    assert monitor.status("training", {}, {}).eta_s == pytest.approx(2_400 / 2.0)
    assert "ETA 20:00)" in monitor.line()


def test_the_stack_writes_its_status_into_the_run_folder(tmp_path):
    config = load_config("smoke", overrides={"run.runs_dir": str(tmp_path), "run.name": "s"})
    run = RunDir.of(config)
    stack = Stack(config, run, "tcp/127.0.0.1:1", actors=1, resume=False)  # nothing started
    stack.report(StackMonitor(config.pace.total_env_steps), "training")
    status = RunStatus.read(run.status)
    assert (status.phase, status.total_env_steps, status.pids) == ("training", 20_000, {})
    assert status.restarts == {"replay": 0, "recorder": 0, "learner": 0, "actor-0": 0}


def job(tmp_path, phase: str, trained_at_start: float = 0.0) -> "grid_job.RunJob":
    options = grid_job.Options(tmp_path, 1000, trials=1, actors=None, extra=(), progress_s=30.0)
    spec = grid_job.RunSpec("bmc", 50, 0)
    run_job = grid_job.RunJob(1, 2, spec, options, stopping=None, phase=phase, trained_at_start=trained_at_start)
    options.run_dir(spec).mkdir(parents=True, exist_ok=True)
    return run_job


def test_a_training_run_is_followed_by_its_stacks_status_not_an_older_one(tmp_path):
    training = job(tmp_path, "train", trained_at_start=0.2)
    path = training.options.run(training.spec).status
    RunStatus(phase="stopped", env_steps=900, total_env_steps=1000, time=training.started_at - 60).write(path)
    assert training.latest_line() == "" and training.trained() == 0.2  # an earlier stack's
    RunStatus(phase="training", env_steps=400, total_env_steps=1000, updates=20, mean_return=1.5, eta_s=95,
              restarts={"actor-0": 1}, time=time.time()).write(path)
    assert training.latest_line() == ("env steps 400/1,000 (40.0%), updates 20, return(100) 1.50, restarts 1, "
                                      "ETA 1:35")
    assert training.trained() == 0.4
    path.write_text("{")  # a damaged file is no status
    assert training.latest_line() == "" and training.trained() == 0.2


class Thread:
    def __init__(self, alive: bool) -> None:
        self.alive = alive

    def is_alive(self) -> bool:
        return self.alive


def test_the_grid_line_counts_runs_done_and_the_steps_trained(tmp_path):
    finished, waiting = job(tmp_path, "done"), job(tmp_path / "other", "waiting", trained_at_start=0.25)
    finished.thread = Thread(alive=False)
    line = experiments.GridStatus([finished, waiting]).line()
    assert line.startswith("grid: 1/2 runs done, 62.5% of the budgets trained, elapsed 0:00, ETA ")


def training_job(tmp_path, eta_s: float | None, elapsed_s: float) -> "grid_job.RunJob":
    running = job(tmp_path, "train")
    running.thread, running.started = Thread(alive=True), time.monotonic() - elapsed_s
    if eta_s is not None:
        RunStatus(phase="training", env_steps=400, total_env_steps=1000, eta_s=eta_s,
                  time=time.time()).write(running.options.run(running.spec).status)
    return running


def test_the_grid_eta_counts_runs_the_running_ones_own_etas_then_the_waiting_in_waves(tmp_path):
    running = [training_job(tmp_path / "a", 600, 1200), training_job(tmp_path / "b", 300, 1500)]
    waiting = [job(tmp_path / name, "waiting") for name in ("c", "d", "e")]
    grid = experiments.GridStatus(running + waiting, parallel=2)
    # before any run ended, a run looks to take 1,800 s; 3 waiting runs, 2 at a time, are 2 waves
    assert grid.remaining_s() == pytest.approx(600 + 2 * 1800, abs=2)
    done = job(tmp_path / "f", "done")
    done.thread, done.took_s = Thread(alive=False), 1000.0
    grid = experiments.GridStatus(running + waiting + [done], parallel=2)
    assert grid.remaining_s() == pytest.approx(600 + 2 * 1000, abs=2)  # the runs that ended set the pace
    unknown = training_job(tmp_path / "g", None, 10)  # its stack has no ETA yet (the random phase)
    assert experiments.GridStatus([unknown] + waiting, parallel=2).remaining_s() is None
    assert "ETA ?" in experiments.GridStatus([unknown] + waiting, parallel=2).line()


def test_held_episodes_are_logged_once_per_period_with_their_count(caplog):
    clock = FakeClock()
    holds = HoldLog(10.0, clock)
    with caplog.at_level(logging.INFO, logger="actor"):
        holds.begin()
        clock.now = 5.0
        holds.tick("behind")  # within the period: silent
        clock.now = 6.0
        holds.end()
        clock.now = 7.0
        holds.begin()
        clock.now = 10.0
        holds.tick("behind")
        clock.now = 15.0
        holds.tick("budget")
        clock.now = 20.0
        holds.tick("budget")  # the same hold, still going
    assert [record.getMessage() for record in caplog.records] == [
        "held 2 episode(s) for 9s of the last 10s: the learner is behind",
        "held 1 episode(s) for 10s of the last 10s: the run's step budget is spent"]


def test_what_a_run_has_trained_comes_from_its_checkpoint(tmp_path):
    short, fresh = RunDir(tmp_path / "short"), RunDir(tmp_path / "fresh")
    save_checkpoint(short.checkpoints, {"clock": {"env_steps": 400}})
    fresh.root.mkdir()
    assert run_progress.trained_share(short.root, 1000) == 0.4
    assert run_progress.trained_share(short.root, 300) == 1.0  # trained, waiting for its curve
    assert run_progress.trained_share(fresh.root, 1000) == 0.0
    short.checkpoint.write_bytes(b"damaged")
    assert run_progress.trained_share(short.root, 1000) == 0.0


def test_a_status_file_that_cannot_be_written_is_said_once_and_the_stack_goes_on(tmp_path, capsys):
    config = load_config("smoke", overrides={"run.runs_dir": str(tmp_path), "run.name": "s"})
    stack = Stack(config, RunDir.of(config), "tcp/127.0.0.1:1", actors=1, resume=False)
    RunDir.of(config).status.mkdir()  # a folder where the file should be
    for _ in range(3):
        stack.report(StackMonitor(), "training")
    assert capsys.readouterr().err.count("cannot write the status file") == 1


def test_the_lines_step_rate_is_over_a_minute_so_bursts_from_held_actors_do_not_read_as_zero():
    clock = FakeClock()
    monitor = StackMonitor(100_000, clock=clock)
    env_steps = 30_000
    for second in range(61):  # an actor held by the rate limiter sends a 300-step burst every 10 s
        clock.now = float(second)
        env_steps += 300 if second and second % 10 == 0 else 0
        monitor.on_replay_stats(replay_stats(env_steps), "k")
    assert "steps/s   30.0 |" in monitor.line()  # 1,800 steps in 60 s, though the last second added none


def test_a_rate_with_min_rises_reaches_back_to_the_sample_before_the_earliest_of_them():
    clock = FakeClock()
    sparse, plain = Eta(0, window_s=10.0, clock=clock, min_rises=2), Eta(0, window_s=10.0, clock=clock)
    for clock.now, done in [(0, 0), (10, 0), (20, 100), (30, 100), (40, 200), (100, 200)]:
        sparse.update(done)
        plain.update(done)
    assert sparse.per_s() == pytest.approx(200 / 90) and plain.per_s() == 0.0


def test_the_lines_step_rate_reads_sparse_episodes_over_several_arrivals_and_falls_when_they_stop():
    """A paced drive run: a 2,000-step episode about every 67 s (30 steps/s), the replay's stats every second."""
    clock, arrivals = FakeClock(), set(range(30, 900, 67))
    monitor, env_steps, read = StackMonitor(200_000, clock=clock), 28_000, []
    for second in range(1_500):
        clock.now = float(second)
        env_steps += 2_000 if second in arrivals else 0
        monitor.on_replay_stats(replay_stats(env_steps), "k")
        if 300 <= second < 900:
            read.append(monitor.env_step_speed.per_s())
    assert 29.0 < min(read) and max(read) < 40.0  # 4 arrivals over 3 to 4 intervals; never 0 between two
    assert monitor.env_step_speed.per_s() < 10.0  # ten minutes without an episode


def test_a_rate_needs_time_between_two_samples():
    clock = FakeClock()
    eta = Eta(10, clock=clock)
    eta.update(3)
    assert eta.per_s() is None
    eta.update(4)
    assert eta.per_s() is None
    clock.now = 2.0
    eta.update(3)
    assert eta.per_s() == 0.0 and eta.remaining_s() is None


def test_the_learners_metrics_give_the_gradients_norm_over_the_period_and_then_forget_it(tmp_path):
    service = LearnerService(load_config("smoke", overrides={"run.runs_dir": str(tmp_path)}))
    prefetcher = Prefetcher(lambda request: None, 4, 10, depth=1)
    try:
        metrics = LearnerMetrics(service, prefetcher)
        for loss, norm in ((0.5, 2.0), (0.4, None), (0.3, 6.0)):
            metrics.on_update(UpdateResult(1, loss, *([np.zeros((1, 1))] * 4), grad_norm=norm))
        stats = metrics.report()
        assert (stats.grad_norm, stats.grad_norm_max, stats.loss) == (4.0, 6.0, pytest.approx(0.4))
        assert math.isnan(metrics.report().grad_norm)  # none measured since
    finally:
        prefetcher.close()
