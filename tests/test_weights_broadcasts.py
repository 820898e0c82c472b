"""Weights broadcasts that scale: broadcasts by time as well as by updates, compact encodings that
actors load within a stated tolerance, and Zenoh shared memory between the processes of one host."""

import dataclasses
import multiprocessing

import msgpack
import numpy as np
import pytest
import torch

from actor.acting import Actor
from common.config_values import load_config
from common.network import D3RQN, weights_to_numpy
from common.schema.fields import ConfigError
from common.transport import loopback_endpoint
from common.wire.envelope import decode, encode
from common.wire.errors import WireError
from common.wire.messages import Weights
from common.wire.weights_encoding import WEIGHTS_ENCODINGS
from deploy.bench.weights_encoding import BFLOAT16_PASS, compare, drives
from learner.service import Cadence, LearnerService
from replay.recorder.arrival import Arrival, peek
from replay.recorder.recorder import WeightsSampler
from tests import weights_peers
from tests.cpu_support import needs_bfloat16
from tests.test_status_lines import FakeClock

# What docs/architecture.md states, measured by deploy/bench/weights_encoding.py on 4,000 frames: at most this
# share of greedy actions changes, and |Q| moves by at most this fraction of the largest |Q|; for the
# compact encodings and for the actor's bfloat16 pass (actor.inference).
TOLERANCE = {"float16": (0.01, 1e-3), "bfloat16": (0.01, 1e-2), BFLOAT16_PASS: (0.01, 1e-2)}
COMPACT = ("float16", "bfloat16")


def small_config(tmp_path, **overrides):
    return load_config("smoke", overrides={"network.lstm_units": 16, "run.runs_dir": str(tmp_path), **overrides})


def float32_tensors(seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {"conv.weight": rng.normal(0, 0.05, (8, 3, 4, 4)).astype(np.float32),
            "lstm.bias": rng.normal(0, 3.0, 64).astype(np.float32)}


# --- broadcasting by time as well as by updates ---------------------------------------------------

def test_without_a_period_the_weights_go_out_every_n_updates_only():
    clock = FakeClock()
    schedule = Cadence(every=5, period_s=0.0, clock=clock)
    due = []
    for updates in range(1, 16):
        clock.now += 10.0  # however long an update takes
        due.append(schedule.due(updates))
    assert [updates for updates, yes in zip(range(1, 16), due) if yes] == [5, 10, 15]


def test_a_period_broadcasts_between_the_counted_updates_and_restarts_at_each_broadcast():
    clock = FakeClock()
    schedule = Cadence(every=50, period_s=1.0, clock=clock)
    sent = []
    for updates in range(1, 101):
        clock.now += 0.3  # 3.3 updates a second: the time rule comes first
        if schedule.due(updates):
            sent.append(updates)
    assert sent[:3] == [4, 8, 12] and 50 in sent and 100 in sent
    assert 52 not in sent and 53 not in sent and 54 in sent  # update 50's broadcast restarted the period
    assert all(later - earlier <= 4 for earlier, later in zip(sent, sent[1:]))


def test_a_slow_learner_broadcasts_after_every_update_once_the_period_has_passed():
    clock = FakeClock()
    schedule = Cadence(every=50, period_s=1.0, clock=clock)
    clock.now += 5.0
    assert schedule.due(1) and not schedule.due(2)


def test_a_fast_learner_broadcasts_no_sooner_than_the_floor():
    clock = FakeClock()
    schedule = Cadence(every=50, period_s=0.0, clock=clock, min_period_s=0.5)
    sent = []
    for updates in range(1, 401):
        clock.now += 1 / 256  # 256 updates a second: every 50 updates would be 5 broadcasts a second
        if schedule.due(updates):
            sent.append(updates)
    assert sent == [128, 256, 384]  # owed from update 50 (then 150, 300), due once 0.5 s (128 updates) passed


def test_a_learner_slower_than_the_floor_keeps_its_count():
    clock = FakeClock()
    schedule = Cadence(every=50, period_s=0.0, clock=clock, min_period_s=0.5)
    sent = []
    for updates in range(1, 201):
        clock.now += 1 / 64  # every 50 updates is every 0.78 s
        if schedule.due(updates):
            sent.append(updates)
    assert sent == [50, 100, 150, 200]


def test_the_period_and_the_encoding_are_checked_options():
    config = load_config("paper")
    assert (config.learner.weights_period_s, config.learner.weights_encoding) == (0.0, "float32")
    assert not config.transport.shared_memory  # opt-in: see its help
    with pytest.raises(ConfigError, match="learner.weights_period_s"):
        load_config("paper", overrides={"learner.weights_period_s": -1.0})
    with pytest.raises(ConfigError, match="learner.weights_min_period_s"):
        load_config("paper", overrides={"learner.weights_min_period_s": -1.0})
    with pytest.raises(ConfigError, match="learner.weights_encoding"):
        load_config("paper", overrides={"learner.weights_encoding": "int8"})


# --- encodings --------------------------------------------------------------------------------------

@pytest.mark.parametrize("encoding", sorted(WEIGHTS_ENCODINGS))
def test_every_encoding_round_trips_through_the_wire(encoding):
    tensors = float32_tensors()
    message = decode(encode(Weights.from_float32(4, tensors, encoding, created=1.0)), Weights)
    assert (message.version, message.encoding, message.created) == (4, encoding, 1.0)
    received = message.to_float32()
    relative = {"float32": 0.0, "float16": 2.0 ** -11, "bfloat16": 2.0 ** -8}[encoding]  # half an ulp
    for name, array in tensors.items():
        assert received[name].dtype == np.float32 and received[name].shape == array.shape
        assert np.all(np.abs(received[name] - array) <= relative * np.abs(array))


def test_compact_encodings_halve_the_message():
    tensors = {"w": np.random.default_rng(0).normal(size=100_000).astype(np.float32)}
    whole = len(encode(Weights.from_float32(1, tensors)))
    for encoding in COMPACT:
        assert abs(len(encode(Weights.from_float32(1, tensors, encoding))) - whole / 2) < 1000


def test_bfloat16_rounds_as_torch_does():
    values = np.random.default_rng(1).normal(0, 10, 10_000).astype(np.float32)
    values[:4] = [1.0 + 2.0 ** -8, 1.0 + 3 * 2.0 ** -8, -0.0, 3.0e38]  # two ties to even, a signed zero, near max
    received = Weights.from_float32(1, {"w": values}, "bfloat16").to_float32()["w"]
    expected = torch.from_numpy(values).to(torch.bfloat16).float().numpy()
    assert np.array_equal(received.view(np.uint32), expected.view(np.uint32))


@pytest.mark.parametrize("encoding, value", [("float16", 70_000.0), ("bfloat16", 3.4e38)])
def test_a_value_beyond_the_encodings_range_is_refused_when_sending(encoding, value):
    with pytest.raises(WireError, match="beyond") as error:
        Weights.from_float32(1, {"w": np.array([1.0, value], np.float32)}, encoding)
    assert error.value.kind == "weights_encoding"


def test_the_learner_broadcasts_and_serves_its_configured_encoding(tmp_path):
    service = LearnerService(small_config(tmp_path, **{"learner.weights_encoding": "bfloat16"}))
    weights = service.make_weights()
    assert weights.encoding == "bfloat16" and service.serve_latest_weights(None) is weights
    with torch.no_grad():
        service.learner.online.lstm.bias_ih_l0[0] = 1e38  # a diverged weight float16 cannot hold
    service.config.learner.weights_encoding = "float16"
    assert service.make_weights().encoding == "float32"  # sent whole instead, with a warning


def test_an_actor_acts_with_compact_weights_as_with_whole_ones(tmp_path):
    config = small_config(tmp_path)
    tensors = weights_to_numpy(D3RQN(config.network))
    shape = (config.network.frame_height, config.network.frame_width, config.network.frame_channels)
    frame = np.random.default_rng(0).integers(0, 256, shape, dtype=np.uint8)
    actor = Actor(config, actor_id=0)
    q_values = {}
    for version, encoding in enumerate(WEIGHTS_ENCODINGS):
        actor.mailbox.offer_weights(decode(encode(Weights.from_float32(version, tensors, encoding)), Weights))
        actor.apply_mail()
        assert actor.weights_version == version and actor.rejections.total == 0
        actor.batched_q.reset(0)
        q_values[encoding] = actor.batched_q.q_values([0], [frame])[0].numpy()
    for encoding in COMPACT:
        assert np.allclose(q_values[encoding], q_values["float32"], atol=1e-2)


# --- what the compact encodings change in the greedy policy, on real frames --------------------------

@pytest.fixture(scope="module")
def simulator_frames():
    return drives(load_config("paper").env, frames=240, drive_steps=120)


@pytest.mark.parametrize("encoding", [pytest.param(encoding, marks=needs_bfloat16) if encoding == BFLOAT16_PASS
                                      else encoding for encoding in TOLERANCE])
def test_compact_weights_change_the_greedy_actions_within_the_stated_tolerance(simulator_frames, encoding):
    network_config = load_config("paper").network  # the paper's sizes: docs/architecture.md's figures
    torch.manual_seed(0)
    tensors = weights_to_numpy(D3RQN(network_config))
    difference = compare(network_config, tensors, encoding, simulator_frames)
    share, relative_q = TOLERANCE[encoding]
    assert difference.frames == 240
    assert difference.greedy_changed <= share
    assert 0 < difference.max_abs_q_difference <= relative_q * difference.max_abs_q


# --- refused encodings ------------------------------------------------------------------------------

def test_an_unknown_encoding_decodes_and_the_actor_refuses_and_counts_it(tmp_path):
    config = small_config(tmp_path)
    actor = Actor(config, actor_id=0)
    good = Weights.from_float32(3, weights_to_numpy(D3RQN(config.network)), "float16")
    actor.mailbox.offer_weights(good)
    newer = decode(encode(dataclasses.replace(good, version=9, encoding="float8")), Weights)
    actor.mailbox.offer_weights(newer)
    actor.mailbox.offer_latest(newer)
    actor.apply_mail()
    assert actor.weights_version == 3
    assert actor.rejections.values()["rejected_weights_encoding"] == 2


def test_a_known_encoding_with_tensors_of_another_dtype_does_not_decode():
    tensors = float32_tensors()
    for encoding in COMPACT:
        with pytest.raises(WireError, match=f"encoding {encoding}") as error:
            encode(Weights(version=1, tensors=tensors, encoding=encoding))
        assert error.value.kind == "weights_encoding"
    envelope = msgpack.unpackb(encode(Weights.from_float32(1, tensors, "bfloat16")))
    envelope["fields"]["encoding"] = "float16"  # bfloat16 bits that claim to be float16
    with pytest.raises(WireError, match="dtype uint16 is not one of float16") as error:
        decode(msgpack.packb(envelope), Weights)
    assert error.value.kind == "weights_encoding"


def test_the_recorder_samples_compact_weights_by_their_version():
    sampler = WeightsSampler(every=10)
    for version in (0, 5, 10):
        data = encode(Weights.from_float32(version, float32_tensors(), "bfloat16", created=1.0))
        seen = peek(data)
        assert (seen.message_type, seen.version, seen.sender_ns) == ("Weights", version, 1_000_000_000)
        sampler.keep(Arrival("w", data, 0, None, version), seen)
    assert (sampler.kept, sampler.skipped) == (2, 1)
    assert decode(data, Weights).to_float32().keys() == float32_tensors().keys()  # a kept message reads back


# --- shared memory between two processes ---------------------------------------------------------------

def shared_memory_unavailable() -> str:
    """Why this machine cannot give Zenoh shared memory, or "" when it can."""
    try:
        from zenoh import shm
        shm.ShmProvider.default_backend(1 << 20).alloc(1024)
    except Exception as error:  # no zenoh.shm in this build, or no room for a segment
        return f"Zenoh shared memory cannot be had here: {type(error).__name__}: {error}"
    return ""


@pytest.mark.parametrize("shared_memory", [True, False], ids=["shm on", "shm off"])
def test_weights_pass_between_two_processes_with_shared_memory_on_and_off(shared_memory):
    if shared_memory and (reason := shared_memory_unavailable()):
        pytest.skip(reason)
    context = multiprocessing.get_context("spawn")
    stop, report = context.Event(), context.Queue()
    endpoint = loopback_endpoint()
    sender = context.Process(target=weights_peers.publish_weights, args=(endpoint, shared_memory, stop, report))
    receiver = context.Process(target=weights_peers.receive_weights, args=(endpoint, shared_memory, report))
    sender.start()
    receiver.start()
    try:
        first = report.get(timeout=60)
        stop.set()
        second = report.get(timeout=30)
    finally:
        stop.set()
        for child in (sender, receiver):
            child.join(30)
            if child.is_alive():
                child.kill()
    reports = dict([first, second])
    expected = float(weights_peers.example_tensors()["w"][7])
    assert reports["subscriber"] is not None, "no weights arrived"
    version, value, in_shared_memory = reports["subscriber"]
    assert version >= 0 and value == expected
    if shared_memory:
        shared, fallbacks = reports["publisher"]
        assert shared >= 1 and fallbacks == 0 and in_shared_memory >= 1
    else:
        assert reports["publisher"] is None and in_shared_memory == 0
    assert (sender.exitcode, receiver.exitcode) == (0, 0)
