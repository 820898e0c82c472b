"""The run's curves: the series of a log, TensorBoard event files (exported and written live by the
recorder, read back with TensorBoard's own reader), and info, plot and export on a log still being written."""

from __future__ import annotations

import dataclasses
import math
import subprocess
import sys
from pathlib import Path

import pytest
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from common.config import TransportConfig
from common.config_values import load_config
from common.transport import open_session, publisher
from common.keys import Keys
from common.wire.codecs import Message
from common.wire.envelope import encode
from common.exploration.base import Counters
from common.wire.messages import EpisodeRecord, Stats
from deploy.launcher.stack import main as stack_main
from replay.recorder.arrival import Arrival, peek
from replay.recorder.cli import main as log_main
from replay.recorder.plot import updates_start
from replay.recorder.reader import LogError, LogFile
from replay.recorder.recorder import Recorder
from replay.recorder.scalars import OFF_GREEDY_MEAN, RETURN_MEAN, read_series
from replay.recorder.tensorboard_events import EventsWriter
from replay.recorder.writer import LogWriter
from tests.processes import loopback_endpoint, start, stop, wait_for
from wire_examples import example_exploration, example_learner_stats

CONFIG = load_config("smoke", overrides={"recorder.flush_period_s": 0.05})
KEYS = Keys("d3rqn", CONFIG.run.name)
SECOND = 1_000_000_000
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def episode(index: int, length: int, episode_return: float, epsilon: float = 0.5, off_greedy: int = -1) -> EpisodeRecord:
    return EpisodeRecord(actor_id=0, episode_index=index, length=length, episode_return=episode_return,
                         collided=index % 2 == 1, start_set="train", start_index=0, epsilon=epsilon,
                         weights_version=0, wall_time=1.0, time=1.0 + index, off_greedy=off_greedy)


def stats(source: str, **values) -> Stats:
    return Stats(source=source, time=1.0, values=values)


def run_messages(replay_env_steps: int = 0) -> list[tuple[str, Message]]:
    """A short run: the replay's count, three episodes, a learner report before and after updates start."""
    exploration = dataclasses.replace(example_exploration(), epsilon=0.75, counters=Counters(updates=4))
    return [
        (KEYS.metrics_source("actor", 0), episode(0, 10, 1.0, epsilon=1.0)),
        (KEYS.replay_stats, stats("replay", env_steps_total=replay_env_steps, episodes=1, hold_reason="none")),
        (KEYS.metrics_source("learner", 0), example_learner_stats(env_steps=10, updates=0, loss=math.nan,
                                                                  updates_per_s=0.0, env_steps_per_update=None,
                                                                  start_env_steps=None)),
        (KEYS.metrics_source("actor", 0), episode(1, 20, 3.0, epsilon=0.75, off_greedy=2)),
        (KEYS.exploration, exploration),
        (KEYS.metrics_source("actor", 0), episode(2, 30, 5.0, epsilon=0.5, off_greedy=9)),
        (KEYS.metrics_source("learner", 0), example_learner_stats(env_steps=60, updates=12, loss=0.25,
                                                                  loss_abs_diff=0.5, updates_per_s=3.0,
                                                                  start_env_steps=25.0)),
    ]


def write_log(path: Path, messages: list[tuple[str, Message]], finish: bool = True) -> LogWriter:
    """The messages at log times 1 s, 2 s, ...; the writer flushed (and closed if finish)."""
    writer = LogWriter(path, CONFIG, None)
    for number, (key, message) in enumerate(messages, start=1):
        data = encode(message)
        writer.write(Arrival(key, data, number * SECOND, None, number), peek(data))
    writer.flush()
    if finish:
        writer.close()
    return writer


def read_events(directory: Path) -> dict[str, list[tuple[int, float, float]]]:
    """(step, value, wall time) of every scalar series, as TensorBoard reads them."""
    events = EventAccumulator(str(directory), size_guidance={"scalars": 0})
    events.Reload()
    return {tag: [(event.step, event.value, event.wall_time) for event in events.Scalars(tag)]
            for tag in events.Tags()["scalars"]}


# --- the series ----------------------------------------------------------------------------------------

def test_series_place_episodes_at_env_steps_and_stats_at_their_own_count(tmp_path):
    write_log(tmp_path / "log.mcap", run_messages())
    with LogFile(tmp_path / "log.mcap") as log:
        series = read_series(log)
    returns = series["episode/return"]
    assert [(p.value, p.env_steps, p.episodes) for p in returns] == [(1.0, 10, 1), (3.0, 30, 2), (5.0, 60, 3)]
    assert [p.value for p in series[RETURN_MEAN]] == [1.0, 2.0, 3.0]
    assert [p.value for p in series["episode/collided"]] == [0.0, 1.0, 0.0]
    # the random phase's episode is not counted; the mean is over the counted episodes' steps: 2/20, 11/50
    assert [(p.value, p.env_steps) for p in series["episode/off_greedy_share"]] == [(0.1, 30), (0.3, 60)]
    assert [p.value for p in series[OFF_GREEDY_MEAN]] == [0.1, 0.22]
    loss = series["learner/0/loss"]  # the NaN of the report before updates is left out
    assert [(p.value, p.env_steps, p.episodes, p.updates, p.wall_s) for p in loss] == [(0.25, 60, 3, 12, 7.0)]
    assert [(p.value, p.env_steps) for p in series["exploration/epsilon"]] == [(0.75, 30)]
    assert [p.value for p in series["exploration/counters/updates"]] == [4.0]
    assert [p.value for p in series["replay/stats/episodes"]] == [1.0] and "replay/stats/hold_reason" not in series
    assert updates_start(series) == {"env_steps": 25.0, "episodes": 1}  # 10 env steps by episode 1, 30 by 2


def test_a_log_begun_mid_run_continues_the_runs_env_steps(tmp_path):
    write_log(tmp_path / "log.mcap", run_messages(replay_env_steps=5000))
    with LogFile(tmp_path / "log.mcap") as log:
        series = read_series(log)
    # the replay had counted 5,000 env steps when this log held the first episode's 10
    assert [p.env_steps for p in series["episode/return"]] == [5000, 5020, 5050]
    assert [p.env_steps for p in series["exploration/epsilon"]] == [5020]
    assert [p.env_steps for p in series["learner/0/loss"]] == [60]  # the learner's own count


def test_without_an_env_step_count_episodes_count_from_the_log_start(tmp_path):
    write_log(tmp_path / "log.mcap", [(key, m) for key, m in run_messages(5000) if isinstance(m, EpisodeRecord)])
    with LogFile(tmp_path / "log.mcap") as log:
        assert [p.env_steps for p in read_series(log)["episode/return"]] == [10, 30, 60]


# --- TensorBoard ----------------------------------------------------------------------------------------

def test_export_tensorboard_is_read_back_by_tensorboard(tmp_path, capsys):
    write_log(tmp_path / "log.mcap", run_messages())
    board = tmp_path / "board"
    assert log_main(["export", str(tmp_path / "log.mcap"), "--tensorboard", str(board)]) == 0
    assert "scalar points" in capsys.readouterr().out
    assert not (tmp_path / "export").exists()  # no CSV unless asked for
    events = read_events(board)
    assert events["episode/return"] == [(10, 1.0, 1.0), (30, 3.0, 4.0), (60, 5.0, 6.0)]
    assert [(step, value) for step, value, _ in events["episode/epsilon"]] == [(10, 1.0), (30, 0.75), (60, 0.5)]
    assert events["learner/0/loss"] == [(60, 0.25, 7.0)]
    assert events["learner/0/loss_abs_diff"] == [(60, 0.5, 7.0)]
    assert events["learner/0/updates_per_s"] == [(10, 0.0, 3.0), (60, 3.0, 7.0)]  # none before the start
    assert [(step, value) for step, value, _ in events["learner/0/updates"]] == [(10, 0.0), (60, 12.0)]
    assert events["replay/stats/env_steps_total"] == [(0, 0.0, 2.0)]
    assert events["exploration/epsilon"] == [(30, 0.75, 5.0)]
    assert [value for _, value, _ in events[RETURN_MEAN]] == [1.0, 2.0, 3.0]


def test_export_tensorboard_refuses_a_folder_that_holds_event_files(tmp_path, capsys):
    write_log(tmp_path / "log.mcap", run_messages())
    board = tmp_path / "board"
    assert log_main(["export", str(tmp_path / "log.mcap"), "--tensorboard", str(board)]) == 0
    capsys.readouterr()
    assert log_main(["export", str(tmp_path / "log.mcap"), "--tensorboard", str(board)]) == 1
    error = capsys.readouterr().err
    assert error.count("\n") == 1 and "already holds TensorBoard event files" in error
    assert len(list(board.iterdir())) == 1


def test_the_recorder_writes_the_same_curves_live_as_the_export(tmp_path):
    board = tmp_path / "live"
    recorder = Recorder(LogWriter(tmp_path / "log.mcap", CONFIG, None), CONFIG.recorder,
                        EventsWriter(board, KEYS.root))
    recorder.start()
    for number, (key, message) in enumerate(run_messages(), start=1):
        assert recorder.offer(key, encode(message), number * SECOND)
    assert recorder.offer(KEYS.metrics_source("actor", 0), b"not a wire message", 99 * SECOND)
    recorder.stop()
    with LogFile(tmp_path / "log.mcap") as log:
        assert len(list(log.records())) == len(run_messages()) + 1
    assert log_main(["export", str(tmp_path / "log.mcap"), "--tensorboard", str(tmp_path / "exported")]) == 0
    live = read_events(board)
    assert live == read_events(tmp_path / "exported")
    assert [step for step, _, _ in live["episode/return"]] == [10, 30, 60]


class BrokenBoard:
    def add_wire(self, *args) -> None:
        raise OSError("no space left on device")

    def flush(self) -> None:
        pass

    def close(self) -> None:
        pass


def test_a_failing_tensorboard_writer_is_dropped_and_recording_goes_on(tmp_path):
    recorder = Recorder(LogWriter(tmp_path / "log.mcap", CONFIG, None), CONFIG.recorder, BrokenBoard())
    recorder.start()
    for number, (key, message) in enumerate(run_messages(), start=1):
        recorder.offer(key, encode(message), number * SECOND)
    recorder.stop()
    assert recorder.board is None and recorder.error is None
    with LogFile(tmp_path / "log.mcap") as log:
        assert len(list(log.records())) == len(run_messages())


# --- a log still being written ----------------------------------------------------------------------------

def test_info_plot_and_export_read_a_log_that_is_still_being_written(tmp_path, capsys):
    path = tmp_path / "traffic.mcap"
    messages = run_messages()
    writer = write_log(path, messages[:4], finish=False)  # flushed, not closed: no summary, no footer
    with pytest.raises(LogError, match="recover"):
        LogFile(path)  # a plain open still wants a finished file
    assert log_main(["info", str(path)]) == 0
    out = capsys.readouterr().out
    assert "unfinished" in out and "messages   4 in 3 channels" in out and " 2 records" in out
    for axis in ("env_steps", "episodes"):
        assert log_main(["plot", str(path), "--x", axis, "--output", str(tmp_path / f"{axis}.png")]) == 0
        assert (tmp_path / f"{axis}.png").read_bytes()[:8] == PNG_MAGIC

    for number, (key, message) in enumerate(messages[4:], start=5):  # the recorder goes on and flushes again
        data = encode(message)
        writer.write(Arrival(key, data, number * SECOND, None, number), peek(data))
    writer.flush()
    with LogFile(path, unfinished_ok=True) as log:
        assert not log.finished
        assert [p.value for p in read_series(log)["episode/return"]] == [1.0, 3.0, 5.0]
        assert sum(log.message_counts.values()) == len(messages) and log.time_span_ns == (SECOND, 7 * SECOND)
        assert log.config().run.name == CONFIG.run.name
    assert log_main(["export", str(path), "--tensorboard", str(tmp_path / "board")]) == 0
    assert [step for step, _, _ in read_events(tmp_path / "board")["learner/0/loss"]] == [60]
    writer.close()
    with LogFile(path) as log, LogFile(path, unfinished_ok=True) as same:
        assert log.finished and same.finished and log.message_counts == same.message_counts


def test_a_running_recorder_s_log_and_curves_can_be_read_while_it_records(tmp_path):
    endpoint = loopback_endpoint()
    session = open_session(TransportConfig(mode="peer", listen=[endpoint]))
    path, board, recorder_log = tmp_path / "traffic.mcap", tmp_path / "board", tmp_path / "recorder.log"
    recorder = start(["-m", "replay.recorder.cli", "record", "--preset", "smoke", "--transport.connect", endpoint,
                      "--recorder.flush_period_s", "0.2", "--output", str(path), "--tensorboard", str(board)],
                     recorder_log)
    try:
        publishers = {key: publisher(session, key) for key in {key for key, _ in run_messages()}}
        for key, output in publishers.items():
            wait_for(lambda: output.matched, f"the recorder's subscription of {key}", 30, [recorder_log])
        for key, message in run_messages():
            publishers[key].put(message)

        def episodes_on_disk() -> int:
            try:
                with LogFile(path, unfinished_ok=True) as log:
                    return sum(1 for _ in log.messages(EpisodeRecord))
            except LogError:  # not there yet, or (rarely) caught in the middle of a write
                return 0

        wait_for(lambda: episodes_on_disk() == 3, "the episodes on disk", 30, [recorder_log])
        outputs = [subprocess.run([sys.executable, "-m", "replay.recorder.cli", *command], capture_output=True,
                                  text=True, timeout=60).stdout
                   for command in (["info", str(path)], ["plot", str(path), "--x", "episodes", "--output",
                                                         str(tmp_path / "p.png")])]
        assert "unfinished" in outputs[0] and " 3 records" in outputs[0]
        assert (tmp_path / "p.png").read_bytes()[:8] == PNG_MAGIC
        wait_for(lambda: len(read_events(board).get("learner/0/loss", [])) == 1, "the live loss curve", 30,
                 [recorder_log])
        assert recorder.poll() is None  # all of it while the recorder runs
    finally:
        stop(recorder)
        session.close()
    assert recorder.returncode == 0
    with LogFile(path) as log:  # now finished
        assert sum(1 for _ in log.messages(EpisodeRecord)) == 3
    assert [step for step, _, _ in read_events(board)["episode/return"]] == [10, 30, 60]


# 250-byte chunks: some fill up with the channel record of a message that goes into the next chunk, one
# that names no other new channel (so the reader must look beyond the chunks with new channels)
@pytest.mark.parametrize("chunk_bytes", [4 << 20, 250])
def test_an_unfinished_log_reads_like_the_finished_one(tmp_path, chunk_bytes):
    messages = [message for n in range(1, 13) for message in (
        (KEYS.metrics_source("actor", 0), stats("actor", episodes=n)),
        (KEYS.metrics_source("actor", n), stats("actor", episodes=n)))] + run_messages() * 3
    config = load_config("smoke", overrides={"recorder.chunk_mb": chunk_bytes / 2**20})
    writer = LogWriter(tmp_path / "log.mcap", config, None)
    for number, (key, message) in enumerate(messages, start=1):
        data = encode(message)
        writer.write(Arrival(key, data, number * SECOND, None, number), peek(data))
        if number % 4 == 0:
            writer.flush()
    writer.flush()
    unfinished = tmp_path / "unfinished.mcap"
    unfinished.write_bytes((tmp_path / "log.mcap").read_bytes())
    writer.close()
    with LogFile(unfinished, unfinished_ok=True) as live, LogFile(tmp_path / "log.mcap") as done:
        assert live.summary.chunk_indexes == done.summary.chunk_indexes
        assert live.message_counts == done.message_counts and live.time_span_ns == done.time_span_ns
        assert live.metadata() == done.metadata()
        topic = KEYS.metrics_source("learner", 0)
        assert [r.data for r in live.records([topic])] == [r.data for r in done.records([topic])]
        assert [r.data for r in live.records()] == [r.data for r in done.records()]


def test_a_file_cut_between_records_is_read_and_one_cut_inside_a_record_is_refused(tmp_path, capsys):
    writer = LogWriter(tmp_path / "log.mcap", CONFIG, None)
    ends = []
    for number, (key, message) in enumerate(run_messages(), start=1):
        data = encode(message)
        writer.write(Arrival(key, data, number * SECOND, None, number), peek(data))
        writer.flush()
        ends.append((tmp_path / "log.mcap").stat().st_size)
    data = (tmp_path / "log.mcap").read_bytes()
    writer.close()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[:ends[3]])  # what a recorder killed after its fourth flush leaves
    with LogFile(cut, unfinished_ok=True) as log:
        assert sum(log.message_counts.values()) == 4 and len(list(log.records())) == 4
    cut.write_bytes(data[:ends[3] - 7])  # the fourth chunk's message index cut short
    with pytest.raises(LogError, match="ends inside a record.*recover"):
        LogFile(cut, unfinished_ok=True)
    assert log_main(["plot", str(cut), "--output", str(tmp_path / "cut.png")]) == 1
    error = capsys.readouterr().err
    assert error.count("\n") == 1 and "recover" in error and not (tmp_path / "cut.png").exists()


def test_the_stack_refuses_tensorboard_without_the_recorder(capsys):
    assert stack_main(["--preset", "smoke", "--tensorboard", "--recorder.enabled", "false"]) == 2
    assert "recorder.enabled" in capsys.readouterr().err
