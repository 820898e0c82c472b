"""The replay process over real Zenoh: stores episodes, serves traces, shrugs off bad input."""


import numpy as np
import pytest

from common.config import TransportConfig
from common.transport import Keys, open_session, publisher, request, subscribe
from common.wire import Episode, FrameStack, Stats, TraceBatch, TraceBatchRequest, encode
from tests import processes
from tests.processes import loopback_endpoint, start, stop

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
         "--replay.stats_period_s", "0.2"], tmp_path / "replay.log")
    session = open_session(TransportConfig(mode="client", connect=[endpoint]))
    stats: list[dict] = []
    subscription = subscribe(session, Keys("d3rqn", RUN).replay_stats,
                             lambda message, key: stats.append(dict(message.values)), expected=Stats)
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
