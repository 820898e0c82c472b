"""The flight recorder and d3rqn-log: record a real stack run, read it, play it into a fresh replay,
survive a SIGKILL, and refuse damaged files with one clear line."""

from __future__ import annotations

import base64
import dataclasses
import json
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from common.analysis.plotting import trailing_mean
from common.config import Config, TransportConfig
from common.config_values import flat_items, load_config
from common.run_dir import next_free_path
from common.liveliness import alive_keys
from common.transport import open_session, publisher, request, subscribe
from common.keys import Keys
from common.wire.envelope import decode, encode
from common.wire.frames import FrameStack
from common.wire.messages import (Episode, EpisodeRecord, ReplayStats, Stats, TraceBatch,
                                  TraceBatchRequest, Weights, flat_values)
from replay.recorder.arrival import NOT_A_MESSAGE, Arrival, peek, publish_time_ns
from replay.recorder.cli import main as log_main
from replay.recorder.export import collect
from replay.recorder.reader import LogError, LogFile
from replay.recorder.recorder import HandOff, Recorder, WeightsSampler
from replay.recorder.recover import recover
from replay.recorder.views import IMAGE_SCHEMA_NAME, ViewMaker, frame_times_ns
from replay.recorder.writer import LogWriter
from common.wire.metrics import LearnerStats
from tests.processes import loopback_endpoint, router_client, start, stop, wait_for
from wire_examples import example_exploration, example_learner_stats

ROOT = Path(__file__).resolve().parents[1]
RUN = "logrun"
STACK_ENV_STEPS = 3000
STACK_TIMEOUT_S = 90.0


# --- pure pieces ---------------------------------------------------------------------------------

def test_handoff_refuses_what_does_not_fit_and_drains_after_close():
    handoff = HandOff(max_items=2, max_bytes=10)
    assert handoff.offer("a", 4) and handoff.offer("b", 4)
    assert not handoff.offer("c", 1)  # too many items
    assert handoff.take(0) == "a"
    assert not handoff.offer("d", 7)  # 4 + 7 bytes > 10
    assert handoff.offer("e", 6)
    handoff.close()
    assert not handoff.offer("f", 1)
    assert [handoff.take(0), handoff.take(0), handoff.take(0)] == ["b", "e", None]
    assert handoff.drained


def test_weights_sampler_keeps_first_every_n_and_the_newest_at_the_end():
    sampler = WeightsSampler(every=10)
    arrivals = {version: Arrival("w", b"", 0, None, version) for version in range(0, 30, 5)}
    kept = [v for v in sorted(arrivals) if sampler.keep(arrivals[v], peek_of(v))]
    assert kept == [0, 10, 20]
    held = sampler.take_held()
    assert held is not None and held[1].version == 25
    assert (sampler.kept, sampler.skipped) == (4, 2)
    assert sampler.take_held() is None


def peek_of(version):
    return peek(encode(Weights(version=version, tensors={"w": np.zeros(2, np.float32)}, created=1.0)))


def test_publish_time_is_the_senders_then_zenohs_then_the_reception():
    stats = encode(Stats(source="learner", time=1700000000.5, values={}))
    episode = encode(make_episode(steps=3, index=0))
    assert publish_time_ns(Arrival("k", stats, 7, 5, 1), peek(stats).sender_ns) == 1_700_000_000_500_000_000
    assert publish_time_ns(Arrival("k", episode, 7, 5, 1), peek(episode).sender_ns) == 5
    assert publish_time_ns(Arrival("k", episode, 7, None, 1), peek(episode).sender_ns) == 7
    assert peek(b"\xc1 not msgpack") == NOT_A_MESSAGE
    assert peek_of(42).version == 42 and peek_of(42).message_type == "Weights"


def test_frames_end_at_the_episode_and_never_overlap_the_previous_one():
    assert frame_times_ns(3, end_ns=1000, previous_end_ns=None, period_ns=100) == [800, 900, 1000]
    assert frame_times_ns(3, end_ns=1000, previous_end_ns=940, period_ns=100) == [960, 980, 1000]


def test_trailing_mean_by_hand():
    assert np.allclose(trailing_mean([1, 2, 3, 4, 5], 2), [1, 1.5, 2.5, 3.5, 4.5])
    assert np.allclose(trailing_mean([2, 4], 100), [2, 3])


def test_a_log_is_never_overwritten(tmp_path):
    path = tmp_path / "traffic.mcap"
    assert next_free_path(path) == path
    path.touch()
    (tmp_path / "traffic-2.mcap").touch()
    assert next_free_path(path) == tmp_path / "traffic-3.mcap"


# --- the recorder's file, in-process -------------------------------------------------------------

def make_episode(steps: int, index: int) -> Episode:
    frames = np.random.default_rng(index).integers(0, 256, (steps + 1, 66, 200, 3), dtype=np.uint8)
    return Episode(observations=FrameStack.from_array(frames), actions=np.arange(steps) % 5,
                   rewards=np.linspace(0, 1, steps, dtype=np.float32), terminated=True, truncated=False,
                   actor_id=0, start_set="train", start_index=1, weights_version=np.zeros(steps, np.int64),
                   epsilon=0.25, seed=0, episode_index=index)


def small_config(**overrides) -> Config:
    return load_config("smoke", overrides={"recorder.flush_period_s": 0.05, **overrides})


def test_recorder_writes_bytes_times_views_and_counters(tmp_path):
    config = small_config(**{"recorder.images": True})
    keys = Keys("d3rqn", config.run.name)
    path = tmp_path / "log.mcap"
    recorder = Recorder(LogWriter(path, config, ViewMaker(keys.root, 0.1, images=True)), config.recorder)
    recorder.start()
    episode = make_episode(steps=4, index=0)
    sent = {
        keys.episodes: [encode(episode)],
        keys.metrics_source("learner", 0): [encode(example_learner_stats(time=1.5e9 + i, loss=float("nan"), updates=i))
                                            for i in range(3)],
        keys.exploration: [encode(dataclasses.replace(example_exploration(), epsilon=0.5))],
        keys.metrics_source("odd", 0): [b"not a wire message"],
    }
    received = {key: [time.time_ns() + i for i in range(len(payloads))] for key, payloads in sent.items()}
    for key, payloads in sent.items():
        for data, received_ns in zip(payloads, received[key]):
            assert recorder.offer(key, data, received_ns)
    recorder.stop()

    with LogFile(path) as log:
        for key, payloads in sent.items():
            records = list(log.records([key]))
            assert [r.data for r in records] == payloads
            assert [r.sequence for r in records] == list(range(1, len(payloads) + 1))
            assert [r.log_ns for r in records] == received[key]
        stats = list(log.records([keys.metrics_source("learner", 0)]))
        assert [r.publish_ns for r in stats] == [round((1.5e9 + i) * 1e9) for i in range(3)]
        assert [json.loads(r.data)["epsilon"] for r in log.records(["/view/exploration"])] == [0.5]
        assert log.config().run.name == config.run.name and log.keys() == keys
        assert log.recorder_counters()["dropped"] == "0"
        stats_view = [json.loads(r.data) for r in log.records(["/view/metrics/learner/0"])]
        assert [v["updates"] for v in stats_view] == [0, 1, 2] and stats_view[0]["loss"] is None
        images = list(log.records(["/view/camera/actor/0"]))
        assert len(images) == 5 and images[0].message_type == IMAGE_SCHEMA_NAME
        png = base64.b64decode(json.loads(images[-1].data)["data"])
        frame = cv2.cvtColor(cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
        assert np.array_equal(frame, episode.observations.decode(4, 5)[0])
        steps = [json.loads(r.data) for r in log.records(["/view/steps/actor/0"])]
        assert [s["action"] for s in steps] == episode.actions.tolist() and steps[-1]["epsilon"] == 0.25


def test_a_full_handoff_drops_and_counts_instead_of_waiting(tmp_path):
    config = small_config(**{"recorder.queue_messages": 2})
    recorder = Recorder(LogWriter(tmp_path / "log.mcap", config, None), config.recorder)  # writer not started
    results = [recorder.offer("d3rqn/x/episodes", b"m", 0) for _ in range(10)]
    assert results == [True, True] + [False] * 8
    assert recorder.snapshot()["dropped"] == 8 and recorder.snapshot()["dropped:d3rqn/x/episodes"] == 8
    recorder.start()
    recorder.stop()
    with LogFile(tmp_path / "log.mcap") as log:
        assert log.recorder_counters()["dropped"] == "8"
        assert [r.sequence for r in log.records()] == [1, 2]


def flushed_log(path: Path, messages: int, finish: bool = False) -> tuple[list[bytes], int]:
    """A log flushed after every message (one chunk each); unfinished, as a killed recorder leaves it, unless finish.
    Returns the payloads and the size of the file's beginning (header and config)."""
    writer = LogWriter(path, small_config(), None)
    header_bytes = path.stat().st_size  # header and config metadata, flushed at once
    payloads = [encode(Stats(source="learner", time=float(i + 1), values={"i": i})) for i in range(messages)]
    for i, data in enumerate(payloads):
        writer.write(Arrival("d3rqn/default/metrics/learner/0", data, i + 1, None, i + 1), peek(data))
        writer.flush()
    if finish:
        writer.close()
    return payloads, header_bytes


def test_recover_keeps_every_message_before_the_cut(tmp_path):
    source = tmp_path / "crashed.mcap"
    payloads, header_bytes = flushed_log(source, messages=6)
    data = source.read_bytes()
    for cut in range(header_bytes, len(data) + 1, 37):
        (tmp_path / "cut.mcap").write_bytes(data[:cut])
        with pytest.raises(LogError, match="recover"):
            LogFile(tmp_path / "cut.mcap")
        result = recover(tmp_path / "cut.mcap", tmp_path / "fixed.mcap")
        with LogFile(tmp_path / "fixed.mcap") as log:
            got = [r.data for r in log.records()]
            assert got == payloads[:len(got)] and result.messages == len(got)
            assert log.config().run.name == "default"
    assert len(got) == len(payloads)  # the whole file gives back everything


def test_a_damaged_chunk_is_a_clear_error_and_recover_skips_it(tmp_path):
    source = tmp_path / "finished.mcap"
    payloads, _ = flushed_log(source, messages=4, finish=True)
    with LogFile(source) as log:
        second = log.summary.chunk_indexes[1]
    data = bytearray(source.read_bytes())
    data[second.chunk_start_offset + second.chunk_length - 20] ^= 0xFF  # inside the compressed records
    damaged = tmp_path / "damaged.mcap"
    damaged.write_bytes(bytes(data))
    with LogFile(damaged) as log, pytest.raises(LogError, match="damaged"):
        list(log.records())
    result = recover(damaged, tmp_path / "fixed.mcap")
    assert result.chunks_skipped == 1
    with LogFile(tmp_path / "fixed.mcap") as log:
        assert [r.data for r in log.records()] == payloads[:1] + payloads[2:]


@pytest.mark.parametrize("content", [b"", b"hello, this is not MCAP at all" * 10])
def test_cli_refuses_a_bad_file_in_one_line(tmp_path, capsys, content):
    path = tmp_path / "bad.mcap"
    path.write_bytes(content)
    for argv in (["info", str(path)], ["recover", str(path), str(tmp_path / "out.mcap")],
                 ["plot", str(tmp_path / "missing.mcap")]):
        assert log_main(argv) == 1
        error = capsys.readouterr().err
        assert error.count("\n") == 1 and error.startswith(f"d3rqn-log {argv[0]}: ")
    assert not (tmp_path / "out.mcap").exists()


# --- a real stack run ------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def recorded_run(tmp_path_factory):
    """deploy/launcher/stack.py with the smoke preset and one actor, until the learner's step budget is spent."""
    base = tmp_path_factory.mktemp("stack")
    log = base / "stack.log"
    process = start(["deploy/launcher/stack.py", "--preset", "smoke", "--actors", "1", "--run.name", RUN,
                     "--run.runs_dir", str(base / "runs"), "--pace.total_env_steps", str(STACK_ENV_STEPS),
                     "--recorder.flush_period_s", "0.5", "--tensorboard",
                     "--pace.error_buffer_updates", "1e9"],  # neither the actor nor the learner waits for the other
                    log, cwd=ROOT)
    try:
        code = process.wait(STACK_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        stop(process)
        code = None
    run_dir = base / "runs" / RUN
    logs = [log, *sorted((run_dir / "logs").glob("*.log"))]
    assert code == 0, "\n".join(f"--- {p.name}\n{p.read_text(errors='replace')[-2000:]}" for p in logs)
    return run_dir


def test_the_stack_records_its_run(recorded_run):
    with LogFile(recorded_run / "traffic.mcap") as log:
        keys = Keys("d3rqn", RUN)
        expected = load_config(toml_path=recorded_run / "config.toml")
        recorded = flat_items(log.config())
        assert {k: v for k, v in recorded.items() if not k.startswith("transport.")} == \
               {k: v for k, v in flat_items(expected).items() if not k.startswith("transport.")}
        assert {keys.episodes, keys.metrics_source("actor", 0), keys.replay_stats, keys.exploration,
                keys.weights} <= set(log.wire_topics())
        episodes = [m for _, m in log.messages(Episode)]
        records = [m for _, m in log.messages(EpisodeRecord)]
        replay = [flat_values(m) for _, m in log.messages(ReplayStats)]
        assert episodes and [e.episode_index for e in episodes] == [r.episode_index for r in records]
        indexes = [e.episode_index for e in episodes]
        assert indexes == list(range(indexes[0], indexes[0] + len(indexes)))  # no episode missing in between
        # taken, or refused because they arrived after the run closed (in flight at the budget)
        received_by_replay = replay[-1]["inserted"] + replay[-1]["short_dropped"] + replay[-1]["late_episodes"]
        assert indexes[-1] + 1 == received_by_replay  # ... nor at the end (the recorder stops after the actors)
        versions = [peek(r.data).version for r in log.records([keys.weights])]
        assert versions[0] == 0 and versions == sorted(versions)
        learner = [m for _, m in log.messages(LearnerStats)]
        if learner:
            assert versions[-1] == learner[-1].weights_version  # the final weights are kept
        assert log.recorder_counters()["dropped"] == "0"


@pytest.fixture
def fresh_replay(tmp_path):
    endpoint = loopback_endpoint()
    log = tmp_path / "replay.log"
    process = start(["-m", "replay.main", "--preset", "smoke", "--run.name", "fresh", "--transport.mode", "router",
                     "--transport.listen", endpoint, "--replay.stats_period_s", "0.2",
                     "--run.runs_dir", str(tmp_path / "runs")], log)
    session = router_client(endpoint)
    try:  # the replay listens from its token on (after its claim), and `play` does not wait for a replay
        wait_for(lambda: alive_keys(session, Keys("d3rqn", "fresh").liveliness("replay", 0), timeout_s=1.0),
                 "the fresh replay's token", 30, [log])
        yield endpoint, session, log
    finally:
        session.close()
        stop(process)


def test_play_fills_a_fresh_replay_with_the_recorded_episodes(recorded_run, fresh_replay, tmp_path):
    endpoint, session, replay_log = fresh_replay
    fresh = Keys("d3rqn", "fresh")
    with LogFile(recorded_run / "traffic.mcap") as log:
        recorded = [r.data for r in log.records([Keys("d3rqn", RUN).episodes])]
    received, stats = [], []
    lock = threading.Lock()

    def on_episode(sample):
        with lock:
            received.append(sample.payload.to_bytes())

    subscriber = session.declare_subscriber(fresh.episodes, on_episode)
    replay_stats = subscribe(session, fresh.replay_stats, lambda m, k: stats.append(flat_values(m)),
                             expected=ReplayStats)
    try:
        play_log = tmp_path / "play.log"
        player = start(["-m", "replay.recorder.cli", "play", str(recorded_run / "traffic.mcap"), "--keys", "episodes",
                        "--to-run", "fresh", "--speed", "0", "--transport.mode", "client",
                        "--transport.connect", endpoint], play_log)
        assert player.wait(60) == 0, play_log.read_text()
        episodes = [decode(data) for data in recorded]
        steps = sum(len(e) for e in episodes)
        wait_for(lambda: len(received) == len(recorded), "the played episodes", 30, [play_log])
        wait_for(lambda: stats and stats[-1]["env_steps_total"] == steps, "the replay to count them", 30, [replay_log])
        with lock:
            assert received == recorded  # byte for byte, in order
        assert stats[-1]["inserted"] + stats[-1]["short_dropped"] == len(episodes)
        batch = request(session, fresh.replay_sample, TraceBatchRequest(request_id=1, batch_size=16, trace_length=10),
                        10.0, expected=TraceBatch)
        assert isinstance(batch, TraceBatch)
        for trace in range(batch.batch_size):
            assert any(matches_window(batch, trace, episode) for episode in episodes)
    finally:
        replay_stats.undeclare()
        subscriber.undeclare()


def matches_window(batch: TraceBatch, trace: int, episode: Episode) -> bool:
    """The trace is a window of the episode: same frame blobs, actions and rewards, byte for byte."""
    steps = batch.trace_length
    blobs = batch.observations.blobs[trace * (steps + 1):(trace + 1) * (steps + 1)]
    for start in range(len(episode) - steps + 1):
        if (episode.observations.blobs[start:start + steps + 1] == blobs
                and np.array_equal(episode.actions[start:start + steps], batch.actions[trace])
                and np.array_equal(episode.rewards[start:start + steps], batch.rewards[trace])):
            return True
    return False


def test_a_killed_recorder_leaves_a_recoverable_file(tmp_path):
    endpoint = loopback_endpoint()
    keys = Keys("d3rqn", "killed")
    session = open_session(TransportConfig(mode="peer", listen=[endpoint]))
    path = tmp_path / "traffic.mcap"
    recorder_log = tmp_path / "recorder.log"
    recorder = start(["-m", "replay.recorder.cli", "record", "--preset", "smoke", "--run.name", "killed",
                      "--transport.connect", endpoint, "--recorder.flush_period_s", "0.2", "--output", str(path)],
                     recorder_log)
    try:
        metrics = publisher(session, keys.metrics_source("learner", 0))
        wait_for(lambda: metrics.matched, "the recorder's subscription", 30, [recorder_log])
        sent = [Stats(source="learner", time=time.time(), values={"updates": i}) for i in range(20)]
        payloads = [encode(message) for message in sent]
        for message in sent:
            metrics.put(message)
        wait_for(lambda: recovered_payloads(path, tmp_path / "probe.mcap", metrics.key) == payloads,
                 "the messages on disk", 30, [recorder_log])
        recorder.send_signal(signal.SIGKILL)
        recorder.wait(10)
        with pytest.raises(LogError, match="recover"):
            LogFile(path)
        done = subprocess.run([sys.executable, "-m", "replay.recorder.cli", "recover", str(path),
                               str(tmp_path / "fixed.mcap")], capture_output=True, text=True, timeout=30)
        assert done.returncode == 0, done.stderr
        with LogFile(tmp_path / "fixed.mcap") as log:
            assert [r.data for r in log.records([metrics.key])] == payloads
            assert log.config().run.name == "killed"
    finally:
        stop(recorder)
        session.close()


def recovered_payloads(live: Path, probe: Path, topic: str) -> list[bytes]:
    """What recover gets out of a file still being written."""
    if not live.exists():
        return []
    recover(live, probe)
    with LogFile(probe) as log:
        return [r.data for r in log.records([topic])] if topic in log.wire_topics() else []


def test_export_plot_and_viewing_file(recorded_run, tmp_path, capsys):
    log_path = str(recorded_run / "traffic.mcap")
    assert log_main(["export", log_path, "--csv", str(tmp_path / "csv"), "--images", str(tmp_path / "view.mcap")]) == 0
    assert log_main(["plot", log_path, "--output", str(tmp_path / "training.png")]) == 0
    assert log_main(["info", log_path]) == 0
    assert "episodes" in capsys.readouterr().out
    with LogFile(log_path) as log:
        tables = collect(log)
    episodes_csv = (tmp_path / "csv" / "episodes.csv").read_text().splitlines()
    assert len(episodes_csv) == 1 + len(tables.episodes) and episodes_csv[0].startswith("log_time,publish_time,")
    replay_csv = (tmp_path / "csv" / "replay_stats.csv").read_text().splitlines()
    assert len(replay_csv) == 1 + len(tables.stats["replay/stats"]) and "env_steps_total" in replay_csv[0]
    assert (tmp_path / "training.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    with LogFile(tmp_path / "view.mcap") as view:
        images = next(view.records(["/view/camera/actor/0"]))
        assert images.message_type == IMAGE_SCHEMA_NAME
        png = base64.b64decode(json.loads(images.data)["data"])
        assert cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR).shape == (66, 200, 3)


def test_the_stack_writes_the_curves_live_as_the_export_does(recorded_run, tmp_path):
    live = recorded_run / "tensorboard"
    assert log_main(["export", str(recorded_run / "traffic.mcap"), "--tensorboard", str(tmp_path / "board")]) == 0
    assert read_events(live) == read_events(tmp_path / "board")
    with LogFile(recorded_run / "traffic.mcap") as log:
        records = [message for _, message in log.messages(EpisodeRecord)]
    returns = read_events(live)["episode/return"]
    assert [value for _, value in returns] == pytest.approx([record.episode_return for record in records])
    assert [step for step, _ in returns] == np.cumsum([record.length for record in records]).tolist()


def read_events(directory: Path) -> dict[str, list[tuple[int, float]]]:
    events = EventAccumulator(str(directory), size_guidance={"scalars": 0})
    events.Reload()
    return {tag: [(event.step, event.value) for event in events.Scalars(tag)] for tag in events.Tags()["scalars"]}


def test_a_truncated_log_is_one_line_and_no_traceback(recorded_run, tmp_path):
    data = (recorded_run / "traffic.mcap").read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[:len(data) // 2])
    done = subprocess.run([sys.executable, "-m", "replay.recorder.cli", "info", str(cut)], capture_output=True, text=True,
                          timeout=30)
    assert done.returncode == 1
    assert done.stderr.count("\n") == 1 and "Traceback" not in done.stderr and "recover" in done.stderr
