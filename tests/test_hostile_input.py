"""Each consumer checks what it takes against the run: refused input is counted by kind, and nothing it
refuses changes what it holds (the replay's episodes, the learner's clock, the actor's weights and hold)."""

import dataclasses
import logging
import threading
import time

import numpy as np
import pytest
import zstandard

from actor.mailbox import Mailbox
from actor.acting import Actor
from common.config_values import load_config
from common.exploration.base import Counters
from common.exploration.boltzmann import SoftmaxConfig
from common.exploration.build import make_strategy
from common.exploration.vdbe import VdbeState
from common.wire.exploration_state import exploration_message
from common.network import D3RQN, weights_to_numpy
from common.rejections import Rejections
from common.wire.envelope import decode, encode
from common.wire.errors import WireError
from common.wire.frames import FrameStack
from common.wire.messages import Episode, ExplorationState, Stats, TraceBatch, TraceBatchRequest, Weights, flat_values
from common.wire.run_shape import RunShape, check_episode, stat_number
from deploy.launcher.stack import StackMonitor
from learner.prefetch import Prefetcher
from learner.service import MAX_FAILED_IN_A_ROW, LearnerService
from replay.service import MAX_PENDING, ReplayService
import hostile
from wire_examples import example_learner_stats, example_rate, example_replay_stats

SIZE, STEPS = 36, 12


def small_config(tmp_path=None, **overrides):
    values = {"network.frame_height": SIZE, "network.frame_width": SIZE, "network.lstm_units": 16,
              "learner.trace_length": 4, "learner.n_mask": 2, "learner.batch_size": 3}
    if tmp_path is not None:
        values["run.runs_dir"] = str(tmp_path)
    return load_config("smoke", overrides={**values, **overrides})


def episode(index: int = 0, steps: int = STEPS, shape=(SIZE, SIZE, 3), incarnation: int = 7) -> Episode:
    frames = np.random.default_rng(index).integers(0, 60, (steps + 1, *shape), dtype=np.uint8)
    return Episode(observations=FrameStack.from_array(frames), actions=np.arange(steps, dtype=np.int64) % 5,
                   rewards=np.full(steps, 0.5, np.float32), terminated=True, truncated=False, actor_id=1,
                   start_set="train", start_index=0, weights_version=np.full(steps, -1, np.int64), epsilon=1.0,
                   seed=0, episode_index=index, incarnation=incarnation)


def corrupt_blob(blob: bytes) -> bytes:
    """Same zstd header (declares the right size), damaged content: only decompressing finds it."""
    damaged = bytearray(blob)
    damaged[len(damaged) // 2] ^= 0xFF
    return bytes(damaged)


def misfits() -> dict[str, Episode]:
    """One well-formed episode per way of not fitting the run (smoke: 5 actions, at most 60 steps)."""
    corrupt = episode(1)
    corrupt.observations = FrameStack([*corrupt.observations.blobs[:5], corrupt_blob(corrupt.observations.blobs[5]),
                                       *corrupt.observations.blobs[6:]], (SIZE, SIZE, 3))
    return {
        "frame_shape": episode(2, shape=(SIZE, SIZE + 4, 3)),
        "frames_corrupt": corrupt,
        "actions": dataclasses.replace(episode(3), actions=np.full(STEPS, 5, np.int64)),
        "rewards": dataclasses.replace(episode(4), rewards=np.full(STEPS, 1e30, np.float32)),
        "length": episode(5, steps=61),
        "weights_version": dataclasses.replace(episode(6), weights_version=np.full(STEPS, -9, np.int64)),
    }


# --- the wire's checks ---------------------------------------------------------------------------

@pytest.mark.parametrize("kind", misfits().keys())
def test_check_episode_names_each_misfit(kind):
    shape = RunShape.of(small_config())
    with pytest.raises(WireError) as raised:
        check_episode(misfits()[kind], shape)
    assert raised.value.kind == kind
    check_episode(episode(), shape)


def test_a_corrupt_blob_passes_decoding_but_not_the_check():
    """The bug of issue 12: decode checks headers only, so this blob used to be stored."""
    damaged = misfits()["frames_corrupt"]
    zstandard.get_frame_parameters(damaged.observations.blobs[5])  # the header is fine
    with pytest.raises(WireError, match="frame 5"):
        damaged.observations.verify()


@pytest.mark.parametrize("value, expected", [
    (3, 3), (3.0, 3), (2.5, None), ("3", None), (True, None), (None, None), (float("nan"), None),
    (float("inf"), None), (-1, None), (10**6, None)])
def test_stat_number_takes_only_sound_counts(value, expected):
    assert stat_number({"n": value}, "n", integer=True, minimum=0, maximum=1000) == expected
    assert stat_number({}, "n") is None and stat_number("not a dict", "n") is None


def test_rejections_count_every_one_and_log_one_line_per_kind_per_period(caplog):
    now = [0.0]
    rejections = Rejections(logging.getLogger("test"), period_s=10.0, clock=lambda: now[0])
    with caplog.at_level(logging.WARNING):
        for _ in range(50):
            rejections.reject("junk", "bad")
        rejections.reject("other", "worse")
        now[0] = 11.0
        rejections.reject("junk", "bad again")
    assert rejections.values() == {"rejected_junk": 51, "rejected_other": 1, "rejected_total": 52}
    lines = [record.getMessage() for record in caplog.records]
    assert len(lines) == 3 and "(49 similar suppressed)" in lines[2]


# --- the replay ------------------------------------------------------------------------------------

class HeldQuery:
    def __init__(self, request) -> None:
        self.request, self.received, self.answer = request, time.monotonic(), None

    def reply(self, message):
        self.answer = message
        return True

    def reply_error(self, text):
        self.answer = text
        return True

    def drop(self):
        self.answer = "dropped"


def test_the_replay_stores_only_episodes_that_fit_and_says_why(tmp_path):
    service = ReplayService(small_config(tmp_path))
    for index in range(3):
        service.on_episode(episode(index))
    before = [stored.frames.blobs for stored in service.store.episodes()]
    for misfit in misfits().values():
        service.on_episode(misfit)
    service.on_episode(Stats(source="x", time=0.0, values={}), "d3rqn/r/episodes")  # a valid message, wrong type
    service.on_episode(episode(2))  # again: a duplicate
    stats = flat_values(service.stats())
    assert {kind: stats.get(f"rejected_episode_{kind}") for kind in (*misfits(), "wrong_type", "duplicate")} == \
        dict.fromkeys((*misfits(), "wrong_type", "duplicate"), 1)
    assert stats["episodes"] == 3 and stats["env_steps_total"] == 3 * STEPS and stats["rejected_total"] == 8
    assert [stored.frames.blobs for stored in service.store.episodes()] == before
    batch = service.store.sample(8)
    assert batch.observations_array().shape == (8, 5, SIZE, SIZE, 3)  # every stored frame decodes


def test_the_replay_refuses_requests_it_cannot_serve_and_holds_a_bounded_number(tmp_path):
    service = ReplayService(small_config(tmp_path))
    wrong_type = HeldQuery(Stats(source="x", time=0.0, values={}))
    wrong_size = HeldQuery(TraceBatchRequest(request_id=1, batch_size=3, trace_length=9))
    for query in (wrong_type, wrong_size):
        service.on_sample_request(query)
    held = [HeldQuery(TraceBatchRequest(request_id=n, batch_size=3, trace_length=4)) for n in range(MAX_PENDING + 5)]
    for query in held:
        service.on_sample_request(query)  # no episodes yet: held
    stats = flat_values(service.stats())
    assert stats["pending_requests"] == MAX_PENDING and stats["rejected_request_overflow"] == 5
    assert stats["rejected_request_wrong_type"] == 1 and stats["rejected_request_size"] == 1
    assert all(isinstance(query.answer, str) for query in (wrong_type, wrong_size, *held[MAX_PENDING:]))
    assert all(query.answer is None for query in held[:MAX_PENDING])


def test_the_replay_takes_the_start_rule_the_learner_states_or_its_strategys(tmp_path):
    service = ReplayService(small_config(tmp_path))  # configured for constant epsilon: by episodes
    state = exploration_message(make_strategy(load_config("smoke", overrides={
        "exploration.strategy": "decreasing"}).exploration, 5))  # no rule stated: a learner that predates it
    service.on_exploration(dataclasses.replace(state, strategy="teleport"))  # nor a strategy to read it from
    service.on_exploration(Stats(source="x", time=0.0, values={}))
    stats = flat_values(service.stats())
    assert stats["rejected_exploration_invalid"] == 1 and stats["rejected_exploration_wrong_type"] == 1
    assert service.learner_rule is None and not service.limiter.limit.start_by_steps
    service.on_exploration(state)  # decreasing epsilon's own rule
    assert service.learner_rule == ("decreasing", True) and service.limiter.limit.start_by_steps
    stated = ReplayService(small_config(tmp_path))
    stated.on_exploration(dataclasses.replace(state, start_by_steps=False))  # pace.start_by episodes
    assert stated.learner_rule == ("decreasing", False) and not stated.limiter.limit.start_by_steps


@pytest.mark.parametrize("start_by, by_steps", [("episodes", False), ("steps", True)])
def test_a_start_rule_for_every_strategy_holds_whatever_the_learners_strategy(tmp_path, start_by, by_steps):
    service = ReplayService(small_config(tmp_path, **{"pace.start_by": start_by}))
    assert service.limiter.limit.start_by_steps == by_steps
    for strategy in ("decreasing", "bmc"):
        service.on_exploration(exploration_message(make_strategy(load_config("smoke", overrides={
            "exploration.strategy": strategy}).exploration, 5)))
        assert service.learner_rule == (strategy, by_steps) and service.limiter.limit.start_by_steps == by_steps


def test_a_learner_that_starts_again_is_owed_the_batches_its_predecessor_lost(tmp_path):
    service = ReplayService(small_config(tmp_path))
    for index in range(2):
        service.on_episode(episode(index))
    for _ in range(2):
        assert service._serve_one_locked() is None  # nothing pending yet
        service.limiter.on_served()
    service.on_sample_request(HeldQuery(TraceBatchRequest(request_id=0, batch_size=3, trace_length=4,
                                                          learner_updates=0)))
    stats = flat_values(service.stats())
    assert stats["rate_batches_served"] == 0 and stats["rate_lost_updates"] == 2
    service.on_sample_request(HeldQuery(TraceBatchRequest(request_id=0, batch_size=3, trace_length=4,
                                                          learner_updates=99)))  # more than served: ignored
    assert flat_values(service.stats())["rate_batches_served"] == 0



def test_a_running_learner_is_owed_the_batches_whose_replies_never_reached_it(tmp_path, caplog):
    service = ReplayService(small_config(tmp_path, **{"learner.prefetch": 1}))  # it can hold 4 unused batches
    for index in range(2):
        service.on_episode(episode(index))
    for _ in range(9):
        service.limiter.on_served()
    ask = lambda updates: service.on_sample_request(HeldQuery(TraceBatchRequest(
        request_id=5, batch_size=3, trace_length=4, learner_updates=updates)))
    ask(5)
    assert flat_values(service.stats())["rate_batches_served"] == 9
    with caplog.at_level(logging.WARNING, logger="replay"):
        ask(2)
    stats = flat_values(service.stats())
    assert stats["rate_batches_served"] == 6 and stats["rate_lost_updates"] == 3
    assert "their replies never reached it; owed again" in caplog.text

# --- the learner -----------------------------------------------------------------------------------

def trace_batch(config, **changes) -> TraceBatch:
    B, T = config.learner.batch_size, config.learner.trace_length
    frames = np.random.default_rng(0).integers(0, 256, (B * (T + 1), SIZE, SIZE, 3), dtype=np.uint8)
    batch = TraceBatch(request_id=0, observations=FrameStack.from_array(frames),
                       actions=np.zeros((B, T), np.int64), rewards=np.zeros((B, T), np.float32),
                       terminated=np.zeros((B, T), bool), weights_version=np.zeros((B, T), np.int64),
                       env_steps_total=100, episodes_stored=4)
    return dataclasses.replace(batch, **changes)


def test_the_learner_drops_batches_that_do_not_fit_and_goes_on(tmp_path):
    config = small_config(tmp_path)
    service = LearnerService(config)
    service.start_updates()
    good = trace_batch(config)
    blobs = list(good.observations.blobs)
    blobs[3] = corrupt_blob(blobs[3])
    other_frames = FrameStack.from_array(np.zeros((15, SIZE, SIZE + 1, 3), np.uint8))
    bad = {
        "batch_frames_corrupt": dataclasses.replace(good, observations=FrameStack(blobs, good.observations.frame_shape)),
        "batch_frame_shape": dataclasses.replace(good, observations=other_frames),
        "batch_actions": dataclasses.replace(good, actions=np.full((3, 4), 7, np.int64)),
        "batch_rewards": dataclasses.replace(good, rewards=np.full((3, 4), -1e9, np.float32)),
        "batch_values": dataclasses.replace(good, env_steps_total=10**15),
        "batch_wrong_type": Stats(source="replay", time=0.0, values={}),
    }
    for batch in bad.values():
        assert service.train_on(batch) is None
    assert service.updates == 0 and service.clock.env_steps == 0
    assert service.train_on(good) is not None and service.updates == 1
    counts = service.rejections.values()
    assert {kind: counts.get(f"rejected_{kind}") for kind in bad} == dict.fromkeys(bad, 1)


def test_batches_are_checked_in_the_prefetch_thread_and_refusals_counted_by_the_loop(tmp_path):
    config = small_config(tmp_path)
    service = LearnerService(config)
    service.start_updates()
    good = trace_batch(config)
    replies = iter([Stats(source="replay", time=0.0, values={}), good])
    prefetcher = Prefetcher(lambda request: next(replies, None), config.learner.batch_size,
                            config.learner.trace_length, depth=1, prepare=service.admit)
    try:
        stop = threading.Event()
        refused, admitted = prefetcher.next(stop, timeout_s=10.0), prefetcher.next(stop, timeout_s=10.0)
    finally:
        prefetcher.close()
    assert service.stager is None  # on a CPU the decoded arrays are used where they lie
    assert refused.error is not None and refused.traces is None
    assert admitted.error is None and admitted.traces.observations.shape[0] == config.learner.batch_size
    assert service.rejections.values().get("rejected_batch_wrong_type") is None  # not counted twice
    assert service.train_on(refused) is None and service.train_on(admitted) is not None
    assert service.rejections.values()["rejected_batch_wrong_type"] == 1 and service.updates == 1


def test_a_failing_update_is_dropped_counted_and_the_learner_goes_on_unless_it_always_fails(tmp_path):
    config = small_config(tmp_path)
    service = LearnerService(config)
    service.start_updates()
    real_update, calls = service.learner.update, []

    def flaky(*args, **kwargs):
        calls.append(1)
        if len(calls) == 1:
            raise RuntimeError("a bad moment")
        return real_update(*args, **kwargs)

    service.learner.update = flaky
    assert service.train_on(trace_batch(config)) is None
    assert service.train_on(trace_batch(config)) is not None
    assert service.failed_updates == 1 and service.updates == 1
    service.learner.update = lambda *args, **kwargs: (_ for _ in ()).throw(RuntimeError("broken for good"))
    for _ in range(MAX_FAILED_IN_A_ROW - 1):
        assert service.train_on(trace_batch(config)) is None
    with pytest.raises(RuntimeError, match="broken for good"):
        service.train_on(trace_batch(config))


ABSURD_RATE = example_rate(env_steps=10**15, start_env_steps=900.0)  # beyond the budget plus a full buffer


@pytest.mark.parametrize("stats, rate", [
    (Stats(source="replay", time=0.0, values={"env_steps_total": 500}),  # an older replay's untyped word
     Stats(source="rate_limiter", time=0.0, values={"env_steps": 500, "start_env_steps": 400.0})),
    (example_replay_stats(ABSURD_RATE), ABSURD_RATE),
    (example_rate(), example_replay_stats()),  # each on the other's key
    (Weights(version=1, tensors={}), Weights(version=1, tensors={}))], ids=["untyped", "absurd", "swapped", "weights"])
def test_the_learner_takes_only_the_replays_typed_word_with_counts_that_fit_the_run(tmp_path, stats, rate):
    service = LearnerService(small_config(tmp_path))
    service.on_replay_stats(stats)
    service.on_replay_rate(rate)
    assert service.clock.env_steps == 0 and service.clock.start_env_steps is None and service.episodes_stored == 0
    assert service.rejections.total == 2


def test_the_latest_weights_go_only_to_a_plain_query(tmp_path):
    service = LearnerService(small_config(tmp_path))
    service.make_weights()
    assert service.serve_latest_weights(None) is service.latest_weights
    assert service.serve_latest_weights(Stats(source="x", time=0.0, values={})) is None
    assert service.rejections.values()["rejected_weights_query"] == 1


# --- the actor -------------------------------------------------------------------------------------

def test_the_actor_refuses_weights_of_another_network_and_keeps_the_good_ones(tmp_path):
    config = small_config(tmp_path)
    actor = Actor(config, actor_id=0)
    good = weights_to_numpy(D3RQN(config.network))
    other = weights_to_numpy(D3RQN(dataclasses.replace(config.network, lstm_units=32)))
    renamed = {f"x.{name}": array for name, array in good.items()}
    actor.mailbox.offer_weights(Weights(version=3, tensors=good))
    for version, tensors in ((4, other), (5, renamed), (6, {})):
        actor.mailbox.offer_weights(Weights(version=version, tensors=tensors))
    actor.mailbox.offer_weights(Stats(source="learner", time=0.0, values={}))
    actor.apply_mail()
    assert actor.weights_version == 3
    non_finite = {name: np.full_like(array, np.nan) for name, array in good.items()}  # the wire would refuse these
    actor.mailbox.offer_weights(Weights(version=8, tensors=non_finite))
    actor.apply_mail()
    assert actor.weights_version == 3
    assert all(torch_finite for torch_finite in (np.isfinite(v.numpy()).all() for v in actor.network.state_dict().values()))
    counts = actor.rejections.values()
    assert (counts["rejected_weights_network"], counts["rejected_weights_wrong_type"],
            counts["rejected_weights_values"]) == (3, 1, 1)


@pytest.mark.parametrize("message", [
    Stats(source="rate_limiter", time=0.0, values={"hold_reason": ""}),  # an older replay's untyped word
    example_replay_stats(),  # the stats on the rate's key
    Weights(version=1, tensors={})], ids=["untyped", "stats", "weights"])
def test_a_rate_message_that_says_nothing_sound_leaves_the_last_word(message):
    mailbox = Mailbox()
    mailbox.offer_rate(example_rate(hold_reason="behind"))
    mailbox.offer_rate(message)
    assert mailbox.must_hold() == "behind" and mailbox.rejections.values()["rejected_rate"] == 1


def test_an_actor_refuses_a_rate_counting_more_env_steps_than_its_run_can(tmp_path):
    actor = Actor(small_config(tmp_path), actor_id=0)
    actor.mailbox.offer_rate(example_rate(hold_reason="behind"))
    actor.mailbox.offer_rate(example_rate(env_steps=10**12))  # beyond the budget plus a full buffer
    assert actor.mailbox.must_hold() == "behind" and actor.rejections.values()["rejected_rate_values"] == 1


def test_the_actor_keeps_its_strategy_against_an_unknown_or_broken_state(tmp_path):
    config = small_config(tmp_path, **{"exploration.strategy": "softmax"})
    actor = Actor(config, actor_id=0)
    state = exploration_message(make_strategy(config.exploration, config.network.n_actions))
    for bad in (dataclasses.replace(state, strategy="teleport"), dataclasses.replace(state, strategy="bmc"),
                dataclasses.replace(state, params=(SoftmaxConfig(kappa=-1.0),))):
        actor.mailbox.offer_exploration(bad)
        actor.apply_mail()
    assert actor.strategy is None  # none came that it could follow: it acts uniformly on
    actor.mailbox.offer_exploration(state)
    actor.apply_mail()
    for bad in (dataclasses.replace(state, state=VdbeState(0.5)), dataclasses.replace(state, counters=Counters(-1))):
        actor.mailbox.offer_exploration(bad)
        actor.apply_mail()
    actor.mailbox.offer_exploration(Stats(source="x", time=0.0, values={}))
    assert actor.strategy.name == "softmax" and actor.strategy.sections() == state.params
    counts = actor.rejections.values()
    assert counts["rejected_exploration_invalid"] == 5 and counts["rejected_exploration_wrong_type"] == 1


def test_only_a_complete_valid_exploration_state_passes_the_wire_to_the_actor():
    """The misfit states the flood sends on exploration: the wire refuses each but the complete, valid state of
    another strategy (the subscription counts and logs what it refuses), which the actor then follows."""
    config = small_config()
    actor = Actor(config, actor_id=0)
    actor.follow(exploration_message(make_strategy(config.exploration, config.network.n_actions)))
    refused = 0
    for data in hostile.misfit_exploration(config).values():
        try:
            actor.follow(decode(data, ExplorationState))
        except WireError:
            refused += 1
    assert refused == len(hostile.misfit_exploration(config)) - 1
    assert actor.strategy.name == "softmax" and "rejected_exploration_invalid" not in actor.rejections.values()


# --- the local stack's live line ---------------------------------------------------------------

def test_the_stack_line_takes_only_checked_metrics_and_survives_the_rest():
    monitor = StackMonitor()
    for values in ({"updates": "many", "epsilon": float("nan"), "final": "yes"}, {"updates": 5}):
        with pytest.raises(WireError):  # an older learner's word with missing or wrongly typed values: refused
            decode(encode(Stats(source="learner", time=0.0, values=values)))
    monitor.on_metric(Stats(source="learner", time=0.0, values={"updates": 9}), "d3rqn/r/metrics/learner/0")
    monitor.on_replay_stats(Stats(source="replay", time=0.0, values={"env_steps_total": -3}), "k")
    monitor.on_replay_stats(Weights(version=0, tensors={}), "k")
    monitor.on_metric(ExplorationState(strategy="x", params={}, epsilon=0.5, kappa=0.0, started=False,
                                       counters={}, state={}), "k")
    line = monitor.line(restarts=2)
    assert "updates       0" in line and "env steps         0" in line and line.endswith("restarts 2")
    assert not monitor.learner_final.is_set()
    summary = monitor.summary(load_config("smoke"), {"replay": 1})
    assert summary["updates"] == 0 and summary["restarts"] == {"replay": 1} and not summary["learner_finished"]


def test_a_learner_stopped_by_hand_is_not_finished_in_the_run_summary():
    """Its final metrics come on any clean stop; only a learner that exited by itself paid for its budget."""
    monitor = StackMonitor()
    monitor.on_metric(example_learner_stats(updates=7, final=True), "d3rqn/r/metrics/learner/0")
    assert monitor.learner_final.is_set()
    config = load_config("smoke")
    assert not monitor.summary(config)["learner_finished"]
    assert monitor.summary(config, finished=True)["learner_finished"]
