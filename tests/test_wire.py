import dataclasses
import tracemalloc

import msgpack
import numpy as np
import pytest
import zstandard
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from common.wire.envelope import SCHEMA_VERSION, decode, encode
from common.wire.errors import WireError
from common.wire.frames import FrameStack
from common.wire.messages import (MESSAGE_TYPES, Episode, EpisodeAck, EpisodeRecord, Stats, TraceBatch, TraceBatchRequest,
                                  Weights, flat_values)
from wire_examples import (
    SMALL_FRAME, assert_messages_equal, example_episode, example_messages, example_rate, example_replay_stats,
    example_trace_batch, example_learner_stats, example_actor_stats, example_exploration, random_frames,
)

EXAMPLES = example_messages()


# --- round trips ---------------------------------------------------------------------

def test_examples_cover_every_message_type():
    assert {type(message).__name__ for message in EXAMPLES} == set(MESSAGE_TYPES)


@pytest.mark.parametrize("message", EXAMPLES, ids=lambda m: type(m).__name__)
def test_every_message_type_round_trips(message):
    decoded = decode(encode(message))
    assert_messages_equal(message, decoded)


@pytest.mark.parametrize("message", EXAMPLES, ids=lambda m: type(m).__name__)
def test_decode_with_the_expected_type_accepts_it(message):
    assert type(decode(encode(message), type(message))) is type(message)


def test_the_envelope_carries_schema_version_and_type_tag():
    envelope = msgpack.unpackb(encode(RECORD))
    assert envelope["schema"] == SCHEMA_VERSION and envelope["type"] == "EpisodeRecord"


def test_episode_of_real_frame_size_round_trips_and_rebuilds_the_frames():
    frames = random_frames(4, shape=(66, 200, 3))
    episode = dataclasses.replace(example_episode(steps=3), observations=FrameStack.from_array(frames))
    decoded = decode(encode(episode), Episode)
    np.testing.assert_array_equal(decoded.observations.decode(), frames)
    assert decoded.observations.frame_shape == (66, 200, 3)


def test_encode_converts_lists_and_same_kind_arrays_to_the_declared_dtypes():
    episode = dataclasses.replace(example_episode(steps=2), actions=[1, 4], rewards=[0.5, 1.0],
                                  weights_version=np.array([3, 4], dtype=np.int32))
    decoded = decode(encode(episode), Episode)
    assert decoded.actions.dtype == np.int64 and decoded.rewards.dtype == np.float32
    assert decoded.weights_version.dtype == np.int64
    np.testing.assert_array_equal(decoded.actions, [1, 4])


def test_numpy_scalars_in_dicts_are_encoded_as_plain_values():
    stats = Stats(source="recorder", time=1.0, values={"queue_mb": np.float32(0.5), "received": np.int64(3)})
    assert decode(encode(stats)).values == {"queue_mb": 0.5, "received": 3}
    counts = example_learner_stats(rejected={"rejected_total": np.int64(4)})
    assert decode(encode(counts)).rejected == {"rejected_total": 4}


def test_trace_batch_observations_array_is_batch_major():
    batch = example_trace_batch(batch=2, length=3)
    frames = batch.observations.decode()
    array = decode(encode(batch), TraceBatch).observations_array()
    assert array.shape == (2, 4, *SMALL_FRAME)
    np.testing.assert_array_equal(array[1, 0], frames[4])


# --- frame stacks ----------------------------------------------------------------------

FRAMES = random_frames(7)
STACK = FrameStack.from_array(FRAMES)


@pytest.mark.parametrize("start, stop", [(0, None), (2, 5), (6, 7), (3, 3), (-2, None), (4, 100)])
def test_partial_decode_equals_slicing(start, stop):
    np.testing.assert_array_equal(STACK.decode(start, stop), FRAMES[start:stop])


def test_frame_stack_reports_length_shape_and_compressed_bytes():
    assert len(STACK) == 7 and STACK.frame_shape == SMALL_FRAME
    assert STACK.nbytes == sum(len(blob) for blob in STACK.blobs) > 0


def test_a_stack_holds_about_the_memory_its_bytes_count():
    # the actor caps what it holds (actor.queue_mb, actor.in_flight_mb) by nbytes: that must be what it holds
    frames = np.zeros((50, 96, 96, 3), np.uint8)  # flat frames compress to a few dozen bytes of 27,648
    tracemalloc.start()
    try:
        stack = FrameStack.from_array(frames)
        held = tracemalloc.get_traced_memory()[0]  # what it allocated and still holds: the stack's
    finally:
        tracemalloc.stop()
    per_blob = 100  # a bytes object's header and the list's slot
    assert stack.nbytes < 50 * 100 and held < 2 * stack.nbytes + 50 * per_blob


def test_select_shares_blob_objects_in_the_given_order():
    chosen = STACK.select([5, 1, 1])
    assert [id(blob) for blob in chosen.blobs] == [id(STACK.blobs[i]) for i in (5, 1, 1)]
    np.testing.assert_array_equal(chosen.decode(), FRAMES[[5, 1, 1]])


def test_concat_shares_blob_objects_and_keeps_order():
    other = FrameStack.from_array(random_frames(2, seed=9))
    joined = FrameStack.concat([STACK.select([0, 1]), other])
    assert joined.blobs[0] is STACK.blobs[0] and joined.blobs[2] is other.blobs[0]
    np.testing.assert_array_equal(joined.decode(), np.concatenate([FRAMES[:2], other.decode()]))


def test_concat_refuses_different_frame_shapes():
    other = FrameStack.from_array(random_frames(1, shape=(2, 2, 3)))
    with pytest.raises(WireError, match="frame shapes differ"):
        FrameStack.concat([STACK, other])


def test_from_array_refuses_non_uint8_frames():
    with pytest.raises(WireError, match="uint8"):
        FrameStack.from_array(FRAMES.astype(np.float32))


def test_a_blob_of_another_shape_fails_to_decode():
    wrong = FrameStack.from_array(random_frames(1, shape=(2, 2, 3))).blobs[0]
    stack = FrameStack([STACK.blobs[0], wrong], SMALL_FRAME)
    np.testing.assert_array_equal(stack.decode(0, 1), FRAMES[:1])  # the good frame alone still decodes
    with pytest.raises(WireError, match="frame 1: blob declares 12 bytes"):
        stack.decode()


def test_a_corrupted_blob_fails_its_checksum():
    blob = bytearray(STACK.blobs[0])
    blob[-6] ^= 0xFF  # inside the payload, past the header
    with pytest.raises(WireError, match="frame 0: bad zstd blob"):
        FrameStack([bytes(blob)], SMALL_FRAME).decode()
    with pytest.raises(WireError):
        FrameStack([bytes(blob)], SMALL_FRAME).verify()


def test_trailing_bytes_after_a_blob_are_refused():
    with pytest.raises(WireError, match="bad zstd blob"):
        FrameStack([STACK.blobs[0] + b"junk"], SMALL_FRAME).decode()


# --- malformed input ---------------------------------------------------------------------

def tampered(message, edit) -> bytes:
    """The message encoded, its msgpack envelope changed by edit (in place), re-packed."""
    envelope = msgpack.unpackb(encode(message))
    edit(envelope)
    return msgpack.packb(envelope, use_bin_type=True)


def set_field(name, value):
    return lambda envelope: envelope["fields"].__setitem__(name, value)


def set_array_part(name, part, value):
    return lambda envelope: envelope["fields"][name].__setitem__(part, value)


def zstd_blob(size: int) -> bytes:
    return zstandard.ZstdCompressor().compress(bytes(size))


RECORD = EpisodeRecord(actor_id=1, episode_index=2, length=30, episode_return=12.5, collided=True, start_set="train",
                       start_index=3, epsilon=0.1, weights_version=4, wall_time=1.5, time=1.0)
EPISODE = example_episode(steps=4)
BATCH = example_trace_batch(batch=2, length=3)
WEIGHTS = Weights(version=1, tensors={"w": np.ones((2, 2), dtype=np.float32)})
NAN32 = np.array([np.nan], dtype=np.float32).tobytes()
ACK = EpisodeAck(actor_id=1, incarnation=5, received=np.array([1]), kept=np.array([2, 3]), refused=np.array([4]))
RATE = example_rate()
REPLAY_STATS = example_replay_stats()
LEARNER = example_learner_stats()
ACTOR = example_actor_stats()
EXPLORATION = example_exploration()


def set_rate_field(name, value):
    return lambda envelope: envelope["fields"]["rate"].__setitem__(name, value)

MALFORMED = {
    "schema version": (RECORD, lambda e: e.__setitem__("schema", SCHEMA_VERSION + 1), "schema version 2 is not supported"),
    "schema version as bool": (RECORD, lambda e: e.__setitem__("schema", True), "schema version True"),
    "unknown type": (RECORD, lambda e: e.__setitem__("type", "Teleport"), "unknown message type 'Teleport'"),
    "envelope key missing": (RECORD, lambda e: e.pop("fields"), "expected a map with keys schema, type, fields"),
    "fields not a map": (RECORD, lambda e: e.__setitem__("fields", [1, 2]), "EpisodeRecord: fields must be a map"),
    "missing field": (RECORD, lambda e: e["fields"].pop("episode_index"), r"EpisodeRecord: missing field\(s\) episode_index"),
    "extra field": (RECORD, set_field("colour", "red"), r"EpisodeRecord: unexpected field\(s\) colour"),
    "string for int": (RECORD, set_field("episode_index", "8"), "EpisodeRecord.episode_index: expected an integer, got str"),
    "bool for int": (RECORD, set_field("episode_index", True), "EpisodeRecord.episode_index: expected an integer, got bool"),
    "int for float": (RECORD, set_field("time", 3), "EpisodeRecord.time: expected a float, got int"),
    "bytes for str": (RECORD, set_field("start_set", b"train"), "EpisodeRecord.start_set: expected a string, got bytes"),
    "negative count": (RECORD, set_field("episode_index", -1), "EpisodeRecord.episode_index: -1 is outside"),
    "int beyond int64": (RECORD, set_field("episode_index", 2**64 - 1), "is outside"),
    "infinite time": (RECORD, set_field("time", float("inf")), "EpisodeRecord.time: must be finite"),
    "off-greedy beyond length": (RECORD, set_field("off_greedy", 31), "31 off-greedy actions in 30 steps"),
    "off-greedy below -1": (RECORD, set_field("off_greedy", -2), "EpisodeRecord.off_greedy: -2 is outside"),
    "epsilon above one": (EPISODE, set_field("epsilon", 1.5), r"Episode.epsilon: 1.5 is outside \[0.0, 1.0\]"),
    "array dtype": (EPISODE, set_array_part("actions", "dtype", "int32"), "Episode.actions: expected dtype int64, got int32"),
    "dtype not allowed": (EPISODE, set_array_part("actions", "dtype", "float16"), "'float16' is not one of"),
    "array data short": (EPISODE, set_array_part("actions", "shape", [5]), "32 data bytes do not fill shape"),
    "array ndim": (EPISODE, set_array_part("actions", "shape", [4, 1]), r"expected 1 dimensions, got shape \(4, 1\)"),
    "negative dimension": (EPISODE, set_array_part("actions", "shape", [-4]), "non-negative integers"),
    "array map keys": (EPISODE, lambda e: e["fields"]["actions"].pop("shape"), "expected an array map"),
    "array data not bytes": (EPISODE, set_array_part("actions", "data", "abc"), "data must be bytes"),
    "bool array byte": (BATCH, set_array_part("terminated", "data", b"\x00\x00\x02\x00\x00\x00"), "bytes other than 0 and 1"),
    "nan reward": (EPISODE, set_array_part("rewards", "data", NAN32 * 4), "Episode.rewards: holds NaN"),
    "nan weight": (WEIGHTS, lambda e: e["fields"]["tensors"]["w"].__setitem__("data", NAN32 * 4), "Weights.tensors.w: holds NaN"),
    "empty tensor name": (WEIGHTS, lambda e: e["fields"]["tensors"].__setitem__("", e["fields"]["tensors"]["w"]), "non-empty strings"),
    "created not a float": (WEIGHTS, set_field("created", "now"), "Weights.created: expected a float"),
    "observation count": (EPISODE, lambda e: e["fields"]["observations"]["blobs"].pop(), "4 observations for 4 steps"),
    "reward count": (EPISODE, set_array_part("rewards", "shape", [2, 2]), "Episode.rewards: expected 1 dimensions"),
    "no steps": (EPISODE, lambda e: e["fields"].update(
        actions={"dtype": "int64", "shape": [0], "data": b""}, rewards={"dtype": "float32", "shape": [0], "data": b""},
        weights_version={"dtype": "int64", "shape": [0], "data": b""}), "at least one step"),
    "negative action": (EPISODE, set_array_part("actions", "data", np.array([0, 1, -1, 2]).tobytes()), "negative action"),
    "negative ack index": (ACK, set_array_part("kept", "data", np.array([2, -3]).tobytes()),
                           "EpisodeAck.kept: a negative episode index"),
    "frame blob garbage": (EPISODE, lambda e: e["fields"]["observations"]["blobs"].__setitem__(1, b"garbage"),
                           r"Episode.observations: frame 1: not a zstd frame"),
    "frame blob size": (EPISODE, lambda e: e["fields"]["observations"]["blobs"].__setitem__(0, zstd_blob(10)),
                        "frame 0: blob declares 10 bytes, shape"),
    "frame shape rank": (EPISODE, lambda e: e["fields"]["observations"].__setitem__("shape", [6, 24]), "three positive integers"),
    "frame shape huge": (EPISODE, lambda e: e["fields"]["observations"].__setitem__("shape", [4096, 4096, 3]), "exceeds"),
    "frame blobs not bytes": (EPISODE, lambda e: e["fields"]["observations"].__setitem__("blobs", ["a"]), "list of bytes"),
    "trace shape mismatch": (BATCH, set_array_part("rewards", "shape", [3, 2]), r"TraceBatch.rewards: shape \(3, 2\), expected \(2, 3\)"),
    "terminal inside trace": (BATCH, set_array_part("terminated", "data", b"\x01\x00\x00\x00\x00\x00"),
                              "terminal state before a trace's last step"),
    # an exploration state is read by the strategy it names: its params, state and counters each by their type
    "unknown strategy": (EXPLORATION, set_field("strategy", "teleport"),
                         r"ExplorationState.params: unknown exploration strategy 'teleport'"),
    "strategy not a name": (EXPLORATION, set_field("strategy", 3), "ExplorationState.strategy: expected a string"),
    "another strategy's state": (EXPLORATION, set_field("state", {"epsilon": 0.5}),
                                 r"ExplorationState.state: epsilon not among the fields of BmcPosterior"),
    "state of no strategy": (EXPLORATION, lambda e: e["fields"].update(strategy="softmax", params={"kappa": 0.1}),
                             r"ExplorationState.state: alpha, beta, count, m2, mean not among the fields of NoState \(\)"),
    "another strategy's params": (EXPLORATION, set_field("params", {"lam": 0.2}),
                                  r"ExplorationState.params: exploration param\(s\) lam not among bmc's"),
    "param out of range": (EXPLORATION, lambda e: e["fields"]["params"].__setitem__("alpha0", -5.0),
                           r"ExplorationState.params: exploration.bmc.alpha0: must be > 0, got -5.0"),
    "param as text": (EXPLORATION, lambda e: e["fields"]["params"].__setitem__("alpha0", "30"),
                      "exploration.bmc.alpha0: expected a number, got '30'"),
    "params not a map": (EXPLORATION, set_field("params", [30.0]), "exploration params must be a map, got list"),
    "nan in the state": (EXPLORATION, lambda e: e["fields"]["state"].__setitem__("mean", float("nan")),
                         "ExplorationState.state.mean: expected a finite number, got nan"),
    "negative posterior count": (EXPLORATION, lambda e: e["fields"]["state"].__setitem__("count", -1),
                                 r"ExplorationState.state.count: must be >= 0, got -1"),
    "state missing a field": (EXPLORATION, lambda e: e["fields"]["state"].pop("beta"), "ExplorationState.state: missing beta"),
    "state not a map": (EXPLORATION, set_field("state", [20.0, 30.0]), "ExplorationState.state: expected a map of alpha"),
    "negative counter": (EXPLORATION, lambda e: e["fields"]["counters"].__setitem__("updates", -3),
                         r"ExplorationState.counters.updates: must be >= 0, got -3"),
    "fractional counter": (EXPLORATION, lambda e: e["fields"]["counters"].__setitem__("env_steps", 2.5),
                           "ExplorationState.counters.env_steps: expected an integer, got 2.5"),
    "nested counters": (EXPLORATION, set_field("counters", {"env_steps": {"n": 1}}),
                        "ExplorationState.counters.env_steps: expected an integer"),
    "unknown counter": (EXPLORATION, lambda e: e["fields"]["counters"].__setitem__("steps", 10),
                        "ExplorationState.counters: steps not among the fields of Counters"),
    "stats bool value": (EXAMPLES[5], set_field("values", {"ok": True}), "Stats.values.ok: expected int, float or str, got bool"),
    "stats list value": (EXAMPLES[5], set_field("values", {"xs": [1]}), "expected int, float or str, got list"),
    "unknown hold": (RATE, set_field("hold_reason", "forever"), "RateState.hold_reason: 'forever' is not one of"),
    "mark past the steps": (RATE, set_field("start_env_steps", 5_000.0), "RateState.start_env_steps: 5000.0 lies past"),
    "negative mark": (RATE, set_field("start_env_steps", -1.0), r"RateState.start_env_steps: -1.0 is outside"),
    "served before the start": (RATE, set_field("start_env_steps", None), "48 batches served before updates started"),
    "closed as a number": (RATE, set_field("closed", 1), "RateState.closed: expected a bool, got int"),
    "steps as text": (RATE, set_field("env_steps", "many"), "RateState.env_steps: expected an integer"),
    "nested rate broken": (REPLAY_STATS, set_rate_field("hold_reason", 3), "ReplayStats.rate.hold_reason: expected a string"),
    "nested rate missing a field": (REPLAY_STATS, lambda e: e["fields"]["rate"].pop("env_steps"),
                                    r"ReplayStats.rate: missing field\(s\) env_steps"),
    "nested rate not a map": (REPLAY_STATS, set_field("rate", [1]), "ReplayStats.rate: fields must be a map"),
    "negative episodes": (REPLAY_STATS, set_field("episodes", -5), "ReplayStats.episodes: -5 is outside"),
    "stats counts as text": (REPLAY_STATS, set_field("rejected", {"rejected_total": "x"}), "ReplayStats.rejected.rejected_total"),
    "negative loss": (LEARNER, set_field("loss", -1.0), r"LearnerStats.loss: -1.0 is outside"),
    "learner epsilon above one": (LEARNER, set_field("epsilon", 1.5), r"LearnerStats.epsilon: 1.5 is outside"),
    "updates as text": (LEARNER, set_field("updates", "many"), "LearnerStats.updates: expected an integer, got str"),
    "infinite update rate": (LEARNER, set_field("updates_per_s", float("inf")), "LearnerStats.updates_per_s: must be finite"),
    "final as a number": (LEARNER, set_field("final", 1), "LearnerStats.final: expected a bool, got int"),
    "learner without updates": (LEARNER, lambda e: e["fields"].pop("updates"), r"LearnerStats: missing field\(s\) updates"),
    "negative rejection count": (LEARNER, set_field("rejected", {"rejected_total": -1}),
                                 r"LearnerStats.rejected.rejected_total: -1 is outside"),
    "fractional door count": (LEARNER, set_field("rejected", {"malformed_stats": 1.5}),
                              "LearnerStats.rejected.malformed_stats: expected an integer, got float"),
    "count under a bytes name": (ACTOR, set_field("rejected", {b"rejected_total": 1}), "keys must be strings"),
    "actor behind by less than none": (ACTOR, set_field("weights_behind", -3), "ActorStats.weights_behind: -3 is outside"),
    "actor version below none": (ACTOR, set_field("weights_version", -2), "ActorStats.weights_version: -2 is outside"),
}


@pytest.mark.parametrize("message, edit, error", MALFORMED.values(), ids=MALFORMED.keys())
def test_malformed_message_gives_a_wire_error_naming_the_fault(message, edit, error):
    with pytest.raises(WireError, match=error):
        decode(tampered(message, edit))


@pytest.mark.parametrize("data, error", [
    (encode(RECORD)[:-3], "not a msgpack message"),
    (encode(RECORD) + b"\x00", "not a msgpack message"),
    (b"", "not a msgpack message"),
    (msgpack.packb({1: 2}), "not a msgpack message"),  # integer map keys
    (msgpack.packb([1, "EpisodeRecord", {}]), "not a wire message"),
])
def test_bytes_that_are_no_message_give_a_wire_error(data, error):
    with pytest.raises(WireError, match=error):
        decode(data)


def test_decode_refuses_a_text_argument():
    with pytest.raises(WireError, match="expected bytes, got str"):
        decode("EpisodeRecord")


def test_decode_refuses_an_unexpected_message_type():
    with pytest.raises(WireError, match="expected message type Episode, got EpisodeRecord"):
        decode(encode(RECORD), Episode)


@pytest.mark.parametrize("message, error", [
    (object(), "object is not a wire message type"),
    (dataclasses.replace(EPISODE, actions=np.arange(4.0)), "Episode.actions: expected dtype int64, got float64"),
    (dataclasses.replace(EPISODE, actions=np.arange(3)), "5 observations for 3 steps"),
    (dataclasses.replace(EPISODE, rewards=np.full(4, np.inf)), "Episode.rewards: holds NaN or infinite"),
    (Weights(version=1, tensors={"w": np.ones(2, dtype=np.float16)}), "dtype float16 is not one of"),
    (Weights(version=1, tensors={"w": [[1.0], [1.0, 2.0]]}), "Weights.tensors.w: not an array"),
    (Stats(source="s", time=1.0, values={"pair": (1, 2)}), "Stats.values.pair: expected int, float or str, got tuple"),
    (dataclasses.replace(RECORD, episode_index=1.0), "EpisodeRecord.episode_index: expected an integer, got float"),
    (dataclasses.replace(REPLAY_STATS, rate=RECORD), "ReplayStats.rate: expected a RateState, got EpisodeRecord"),
    (example_rate(hold_reason="later"), "RateState.hold_reason: 'later'"),
])
def test_encode_refuses_invalid_messages(message, error):
    with pytest.raises(WireError, match=error):
        encode(message)


# --- property-based: no input escapes as anything but WireError -------------------------------

ENCODINGS = [encode(message) for message in EXAMPLES]
FUZZ = settings(max_examples=150, derandomize=True, database=None, deadline=None,
                suppress_health_check=[HealthCheck.too_slow])


def decode_everything(data: bytes) -> None:
    """Decodes data and every frame in it; only WireError may come out."""
    try:
        message = decode(data)
    except WireError:
        return
    for f in dataclasses.fields(message):
        value = getattr(message, f.name)
        if isinstance(value, FrameStack):
            try:
                value.decode()
            except WireError:
                pass


@FUZZ
@given(st.binary(max_size=300))
def test_random_bytes_raise_only_wire_error(data):
    decode_everything(data)


@FUZZ
@given(st.sampled_from(ENCODINGS), st.data())
def test_bit_flips_raise_only_wire_error(data, draw):
    flipped = bytearray(data)
    for _ in range(draw.draw(st.integers(1, 4))):
        position = draw.draw(st.integers(0, len(data) - 1))
        flipped[position] ^= 1 << draw.draw(st.integers(0, 7))
    decode_everything(bytes(flipped))


@FUZZ
@given(st.sampled_from(ENCODINGS), st.data())
def test_truncations_and_insertions_raise_only_wire_error(data, draw):
    position = draw.draw(st.integers(0, len(data)))
    if draw.draw(st.booleans()):
        mutated = data[:position]
    else:
        mutated = data[:position] + draw.draw(st.binary(min_size=1, max_size=16)) + data[position:]
    decode_everything(mutated)


MSGPACK_VALUES = st.recursive(
    st.none() | st.booleans() | st.integers(-(2**63), 2**64 - 1) | st.floats() | st.text(max_size=8) | st.binary(max_size=8),
    lambda children: st.lists(children, max_size=4) | st.dictionaries(st.text(max_size=4), children, max_size=4),
    max_leaves=12,
)


@FUZZ
@given(st.sampled_from(EXAMPLES), st.data())
def test_any_value_in_any_field_raises_only_wire_error(message, draw):
    field_names = [f.name for f in dataclasses.fields(message)]
    name = draw.draw(st.sampled_from(field_names))
    value = draw.draw(MSGPACK_VALUES)
    decode_everything(tampered(message, set_field(name, value)))


def test_a_field_with_a_default_may_be_absent_and_others_may_not():
    """Senders older than a field (a recorded log, an older actor) still decode; the default stands."""
    old_episode = tampered(EPISODE, lambda e: e["fields"].pop("incarnation"))
    assert decode(old_episode).incarnation == 0
    old_request = tampered(TraceBatchRequest(request_id=1, batch_size=2, trace_length=3),
                           lambda e: e["fields"].pop("learner_updates"))
    assert decode(old_request).learner_updates == -1
    assert decode(tampered(RECORD, lambda e: e["fields"].pop("off_greedy"))).off_greedy == -1  # not counted
    with pytest.raises(WireError, match=r"missing field\(s\) episode_index"):
        decode(tampered(EPISODE, lambda e: e["fields"].pop("episode_index")))


@pytest.mark.parametrize("data, kind", [
    (b"\x00junk", "undecodable"), (msgpack.packb([1, 2]), "undecodable"),
    (tampered(RECORD, lambda e: e.__setitem__("type", "Teleport")), "undecodable"),
    (tampered(RECORD, set_field("episode_index", "8")), "invalid")])
def test_a_wire_error_names_its_kind(data, kind):
    with pytest.raises(WireError) as raised:
        decode(data)
    assert raised.value.kind == kind
    with pytest.raises(WireError) as raised:
        decode(encode(RECORD), Episode)
    assert raised.value.kind == "wrong_type"


def test_counters_flatten_to_the_rows_logs_keep():
    """A typed message flattens as older logs' Stats did: the nested rate's fields named rate_<field>, dicts
    merged, flags as 0 or 1, and what is None (no start mark, no snapshot yet) left out."""
    rate = example_rate(start_env_steps=None, batches_served=0, env_steps_per_update=None, closed=True)
    flat = flat_values(example_replay_stats(rate))
    assert flat["env_steps_total"] == 1_200 and flat["rate_env_steps"] == 1_200 and flat["rate_closed"] == 1
    assert flat["rejected_total"] == 0 and flat["inserted_per_s"] == 0.5 and flat["snapshots_written"] == 0
    assert "rate_start_env_steps" not in flat and "snapshot_age_s" not in flat and "rate" not in flat
    assert flat_values(example_rate())["start_env_steps"] == 1_000.0
    assert flat_values(Stats(source="x", time=1.0, values={"a": 1})) == {"a": 1}
