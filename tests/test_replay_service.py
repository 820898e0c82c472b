"""The replay process over real Zenoh: stores episodes, serves traces, shrugs off bad input, and
paces the learner and the actors with its rate limiter."""

import dataclasses
import json
import logging
import threading
import time

import numpy as np
import pytest

from common.config_values import load_config
from common.transport import publisher, request, subscribe
from common.keys import Keys
from common.wire.envelope import encode
from common.wire.frames import FrameStack
from common.wire.messages import Episode, RateState, ReplayStats, TraceBatch, TraceBatchRequest, flat_values
from replay.process import counters_path
from replay.service import ReplayService
from tests import processes
from tests.processes import loopback_endpoint, router_client, start, stop

RUN = "replaysvc"
TRACE = 10


def episode(steps: int, index: int) -> Episode:
    frames = np.full((steps + 1, 66, 200, 3), index, dtype=np.uint8)
    return Episode(observations=FrameStack.from_array(frames), actions=np.zeros(steps, np.int64),
                   rewards=np.ones(steps, np.float32), terminated=True, truncated=False, actor_id=0,
                   start_set="train", start_index=0, weights_version=np.zeros(steps, np.int64), epsilon=1.0,
                   seed=0, episode_index=index)


@pytest.fixture
def replay(tmp_path):
    endpoint = loopback_endpoint()
    process = start(
        ["-m", "replay.main", "--preset", "smoke", "--run.name", RUN, "--transport.mode", "router",
         "--transport.listen", endpoint, "--replay.capacity", "3", "--replay.max_message_mb", "1",
         "--replay.stats_period_s", "0.2", "--run.runs_dir", str(tmp_path / "runs"),
         "--env.max_steps", "400"], tmp_path / "replay.log")  # episodes longer than env.max_steps are refused
    session = router_client(endpoint)
    stats: list[dict] = []
    subscription = subscribe(session, Keys("d3rqn", RUN).replay_stats,
                             lambda message, key: stats.append(flat_values(message)), expected=ReplayStats)
    try:
        yield session, stats, process, tmp_path / "replay.log"
    finally:
        subscription.undeclare()
        session.close()
        stop(process)


def wait_for(condition, what: str) -> None:
    processes.wait_for(condition, what, timeout_s=30.0)


def test_stores_serves_and_survives_bad_input(replay):
    session, stats, process, log_path = replay
    keys = Keys("d3rqn", RUN)
    episodes = publisher(session, keys.episodes)
    wait_for(lambda: stats, "replay stats")
    wait_for(lambda: episodes.matched, "the replay's subscription")

    for index in range(1, 5):  # four episodes into a capacity of three: the first is evicted
        episodes.put(episode(12, index))
    episodes.put(episode(5, 9))  # too short for a trace: counted, not stored
    wait_for(lambda: stats[-1]["inserted"] == 4 and stats[-1]["short_dropped"] == 1, "the episodes")

    raw = session.declare_publisher(keys.episodes)
    raw.put(b"\x93not a message")  # malformed
    raw.put(encode(episode(12, 7))[:-40])  # truncated
    raw.put(encode(episode(300, 8)))  # valid and, with flat frames, well under 1 MB: stored
    big = np.random.default_rng(0).integers(0, 256, size=(40, 66, 200, 3), dtype=np.uint8)
    oversized = episode(39, 6)
    oversized.observations = FrameStack.from_array(big)
    raw.put(encode(oversized))  # random frames do not compress: > 1 MB
    wait_for(lambda: stats[-1]["rejected_messages"] >= 3, "the rejections")

    batch = request(session, keys.replay_sample, TraceBatchRequest(request_id=5, batch_size=64, trace_length=TRACE),
                    timeout_s=10.0, expected=TraceBatch)
    assert batch is not None and batch.request_id == 5
    first_pixels = set(batch.observations_array()[:, :, 0, 0, 0].ravel().tolist())
    assert first_pixels <= {2, 3, 4, 8}  # episode 1 evicted, the short and bad ones never stored
    wrong_length = request(session, keys.replay_sample, TraceBatchRequest(request_id=6, batch_size=4, trace_length=3),
                           timeout_s=10.0)
    assert wrong_length is None
    wait_for(lambda: stats[-1]["rejected_requests"] == 1 and stats[-1]["traces_served"] == 64, "the served count")
    latest = stats[-1]
    assert latest["episodes"] == 3 and latest["evicted"] >= 1
    assert process.poll() is None, log_path.read_text()


# --- the rate limiter over the wire ------------------------------------------------------------

def ask(session, request_id: int, results: dict) -> threading.Thread:
    """A trace-batch request in the background; its reply (or None) lands in results[request_id]."""
    def run():
        results[request_id] = request(session, Keys("d3rqn", RUN).replay_sample,
                                      TraceBatchRequest(request_id=request_id, batch_size=2, trace_length=TRACE),
                                      timeout_s=20.0, expected=TraceBatch)
    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    return thread


def test_replies_wait_for_steps_and_actors_wait_for_the_learner(replay, tmp_path):
    """Smoke: updates start at 2 stored episodes, 1 update per 20 env steps, error buffer 2 updates."""
    session, stats, process, log_path = replay
    keys = Keys("d3rqn", RUN)
    rates: list[dict] = []
    rate_subscription = subscribe(session, keys.replay_rate, lambda m, k: rates.append(flat_values(m)),
                                  expected=RateState)
    episodes = publisher(session, keys.episodes)
    wait_for(lambda: episodes.matched and rates, "the replay's subscription and rate message")
    try:
        results: dict = {}
        early = ask(session, 0, results)  # before updates start: held, not refused
        episodes.put(episode(12, 1))
        time.sleep(0.5)
        assert 0 not in results
        episodes.put(episode(12, 2))  # the second stored episode: updates start at 24 env steps
        early.join(20)
        assert results[0] is not None and results[0].env_steps_total == 24
        ask(session, 1, results).join(20)  # 2 served, 0 due: the buffer's two updates ahead
        third = ask(session, 2, results)
        time.sleep(0.5)
        assert 2 not in results  # a third batch would put the learner 3 ahead
        episodes.put(episode(20, 3))  # 20 more steps: 1 update due, so 3 <= 1 + 2
        third.join(20)
        assert results[2] is not None and results[2].env_steps_total == 44
        assert all(r["hold_reason"] == "" for r in rates)

        episodes.put(episode(120, 4))  # 7 due, 3 served: 4 behind, more than 2
        wait_for(lambda: rates[-1]["hold_reason"] == "behind", "the actors told to hold")
        ask(session, 3, results).join(20)
        ask(session, 4, results).join(20)  # 5 served: 2 behind, within the buffer
        wait_for(lambda: rates[-1]["hold_reason"] == "", "the actors released")
        latest = rates[-1]
        assert (latest["env_steps"], latest["batches_served"], latest["start_env_steps"]) == (164, 5, 24)
        assert latest["updates_due"] == pytest.approx(7.0)
        assert latest["env_steps_per_update"] == pytest.approx(140 / 5)
        wait_for(lambda: stats and stats[-1]["rate_batches_served"] == 5, "the counters in the stats")
    finally:
        rate_subscription.undeclare()
    stop(process)
    saved = json.loads(counters_path(load_config("smoke", overrides={
        "run.name": RUN, "run.runs_dir": str(tmp_path / "runs")})).read_text())
    assert (saved["env_steps"], saved["served"], saved["start_mark"]) == (164, 5, 24)


def test_a_resumed_replay_continues_its_counters(tmp_path):
    config = load_config("smoke", overrides={"run.name": RUN, "run.runs_dir": str(tmp_path / "runs")})
    path = counters_path(config)
    path.parent.mkdir(parents=True)
    path.write_text(json.dumps({"version": 1, "env_steps": 5_000, "served": 240, "start_mark": 200.0}))
    endpoint = loopback_endpoint()
    process = start(["-m", "replay.main", "--preset", "smoke", "--run.name", RUN, "--run.runs_dir",
                     str(tmp_path / "runs"), "--transport.mode", "router", "--transport.listen", endpoint,
                     "--replay.stats_period_s", "0.2", "--resume"], tmp_path / "replay.log")
    session = router_client(endpoint)
    stats: list[dict] = []
    subscription = subscribe(session, Keys("d3rqn", RUN).replay_stats, lambda m, k: stats.append(flat_values(m)),
                             expected=ReplayStats)
    try:
        episodes = publisher(session, Keys("d3rqn", RUN).episodes)
        wait_for(lambda: episodes.matched and stats, "the resumed replay")
        assert (stats[-1]["env_steps_total"], stats[-1]["rate_batches_served"]) == (5_000, 240)
        assert stats[-1]["rate_refilling"] == 1 and stats[-1]["rate_hold_reason"] == ""
        for index, steps in enumerate((40, 20, 60)):  # the store restarts empty; the counters go on
            episodes.put(episode(steps, index))
        wait_for(lambda: stats[-1]["env_steps_total"] == 5_120, "the episodes counted")
        latest = stats[-1]
        # smoke: 2 episodes refill the store; their 60 steps move the start mark, the third's are owed
        assert latest["episodes"] == 3 and latest["rate_refilling"] == 0 and latest["rate_refill_env_steps"] == 60
        assert latest["rate_start_env_steps"] == 260 and latest["rate_updates_due"] == pytest.approx(4_860 / 20)
    finally:
        subscription.undeclare()
        session.close()
        stop(process)
    assert "resumed the rate limiter" in (tmp_path / "replay.log").read_text()


# --- the memory budget --------------------------------------------------------------------------

def test_the_budget_check_says_how_many_full_episodes_fit(caplog):
    # 60-step episodes: 61 frames of 3,276.8 B + 60 x 20 B of metadata = 201,084.8 B each;
    # 10 MB = 10,485,760 B holds 52 of them, 5 MB 26, and 50 need 10,054,240 B (9.6 MB)
    config = load_config("smoke", overrides={"replay.capacity": 50, "replay.memory_budget_mb": 10.0})
    with caplog.at_level(logging.INFO, logger="replay"):
        assert ReplayService(config).budget_report(3.2 * 1024, "estimate")
    assert "holds 52 episodes of env.max_steps = 60 steps at 3.20 KB per frame" in caplog.text
    caplog.clear()
    config = load_config("smoke", overrides={"replay.capacity": 50, "replay.memory_budget_mb": 5.0})
    with caplog.at_level(logging.INFO, logger="replay"):
        assert not ReplayService(config).budget_report(3.2 * 1024, "estimate")
    [record] = caplog.records
    assert record.levelno == logging.WARNING and "holds only 26 of 50 episodes" in record.getMessage()
    assert "--replay.memory_budget_mb 10" in record.getMessage()


def test_the_default_budget_holds_2000_full_length_episodes():
    config = load_config("paper", overrides={"replay.capacity": 2000})
    assert config.env.max_steps == 2000
    assert ReplayService(config).budget_report(3.2 * 1024, "the top-down camera's frames")
    assert ReplayService(config).budget_report(4.0 * 1024, "frames a quarter larger")


def test_budget_evictions_below_capacity_are_counted_and_warned(caplog):
    config = load_config("smoke", overrides={"replay.capacity": 10, "replay.memory_budget_mb": 0.001})
    service = ReplayService(config)
    with caplog.at_level(logging.WARNING, logger="replay"):
        for index in range(3):
            service.on_episode(episode(12, index))
    values = flat_values(service.stats())
    assert values["episodes"] == 1 and values["evicted_for_budget"] == 2
    assert "MEMORY BUDGET IS EVICTING" in caplog.text


class FakeQuery:
    """What the reply threads see of a held Zenoh query."""

    def __init__(self, request_id: int) -> None:
        self.request = TraceBatchRequest(request_id=request_id, batch_size=2, trace_length=TRACE)
        self.received = time.monotonic()
        self.answer = None
        self.done = threading.Event()

    def reply(self, message) -> bool:
        self.answer = message
        self.done.set()
        return True

    def reply_error(self, text: str) -> bool:
        self.answer = text
        self.done.set()
        return True

    def drop(self) -> None:
        self.done.set()


def test_a_reply_thread_survives_a_failing_sample(caplog):
    service = ReplayService(load_config("smoke"))
    for index in range(2):
        service.on_episode(episode(12, index))  # updates start: two batches of slack
    real_sample, calls = service.store.sample, []

    def flaky_sample(*args):
        calls.append(args)
        if len(calls) == 1:
            raise RuntimeError("disk on fire")
        return real_sample(*args)

    service.store.sample = flaky_sample
    stop, announced = threading.Event(), []
    thread = threading.Thread(target=service.serve_pending, args=(stop, announced.append))
    thread.start()
    try:
        first, second = FakeQuery(1), FakeQuery(2)
        service.on_sample_request(first)
        assert first.done.wait(10) and first.answer == "sampling failed: RuntimeError: disk on fire"
        service.on_sample_request(second)
        assert second.done.wait(10) and isinstance(second.answer, TraceBatch) and second.answer.request_id == 2
    finally:
        stop.set()
        thread.join(10)
    assert not thread.is_alive() and announced  # the rate message went out
    assert service.limiter.served == 1  # the failed sample was not counted as served


def test_episodes_after_the_run_closed_are_refused_counted_and_announced(caplog):
    config = load_config("smoke", overrides={"pace.total_env_steps": 30, "pace.start_episodes": 1,
                                             "pace.env_steps_per_update": 4.0, "pace.error_buffer_updates": 2.0})
    service = ReplayService(config)
    service.on_episode(episode(12, 0))  # the start mark: 12 steps
    service.on_episode(episode(24, 1))  # 36 >= 30: the budget is spent, 6 updates due
    assert service.limiter.budget_spent and not service.limiter.closed
    stop, announced = threading.Event(), []
    thread = threading.Thread(target=service.serve_pending, args=(stop, announced.append))
    thread.start()
    try:
        for request_id in range(6):
            query = FakeQuery(request_id)
            service.on_sample_request(query)
            assert query.done.wait(10) and isinstance(query.answer, TraceBatch)
        processes.wait_for(lambda: announced and announced[-1].closed, "the close on replay/rate", 10.0)
    finally:
        stop.set()
        thread.join(10)
    with caplog.at_level(logging.INFO):
        service.on_episode(episode(12, 2))  # in flight at the budget, too late
    values = flat_values(service.stats())
    assert (values["episodes"], values["late_episodes"], values["late_env_steps"]) == (2, 1, 12)
    assert values["rate_env_steps"] == 36 and values["rate_closed"] == 1
    assert "the run is closed" in caplog.text


def test_a_request_stating_more_updates_than_the_budget_pays_for_is_refused():
    config = load_config("smoke", overrides={"pace.total_env_steps": 400, "replay.capacity": 5})
    service = ReplayService(config)  # (400 + 5 x 60) / 20 + 2 = 37 updates at most
    query = FakeQuery(3)
    query.request = dataclasses.replace(query.request, learner_updates=38)
    service.on_sample_request(query)
    assert query.done.is_set() and "more than the run's budget pays for (37)" in query.answer
    assert service.rejections.values()["rejected_request_updates"] == 1
