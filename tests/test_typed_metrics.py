"""The learner's and the actors' metrics are typed messages (common/wire/metrics.py); what older senders wrote
as an untyped Stats, live or in a log, decodes into them, and a value its field refuses is a WireError."""

from __future__ import annotations

import math

import pytest

from common.config_values import load_config
from common.keys import Keys
from common.wire.envelope import decode, encode
from common.wire.errors import WireError
from common.wire.messages import Stats
from common.wire.metrics import ActorStats, LearnerStats
from replay.recorder.arrival import Arrival, peek
from replay.recorder.reader import LogFile
from replay.recorder.run_curves import read_run_curves
from replay.recorder.writer import LogWriter
from wire_examples import example_learner_stats

# What a learner wrote before the typed metrics: a figure since dropped (pace_wait_s), none of the later ones
# (grad_norm, kappa, ...), run-time counters, and the final report's flag as 1.
OLD_LEARNER = {"updates": 1_200, "env_steps": 9_000, "loss": 0.02, "loss_abs_diff": 0.004, "epsilon": 0.25,
               "updates_per_s": 4.5, "data_wait_share": 0.5, "pace_wait_s": 3.0, "weights_version": 1_150,
               "precision": "float32", "rejected_batch_shape": 2, "rejected_total": 2, "malformed_stats": 1,
               "env_steps_per_update": 4, "final": 1}
OLD_ACTOR = {"episodes": 7, "episodes_sent": 6, "weights_version": -1, "weights_download_s": 0, "rejected_total": 0}


def old(source: str, values: dict) -> bytes:
    return encode(Stats(source=source, time=1_700_000_000.5, values=values))



def write_log(path, config, key, payloads) -> None:
    """An MCAP log holding the payloads on one key, a second apart, as the recorder writes them."""
    writer = LogWriter(path, config, None)
    for number, data in enumerate(payloads, start=1):
        writer.write(Arrival(key, data, number * 1_000_000_000, None, number), peek(data))
    writer.close()


def test_an_older_learners_stats_decode_into_its_typed_metrics():
    stats = decode(old("learner", OLD_LEARNER))
    assert type(stats) is LearnerStats and stats.time == 1_700_000_000.5
    assert (stats.updates, stats.env_steps, stats.loss, stats.loss_abs_diff) == (1_200, 9_000, 0.02, 0.004)
    assert stats.env_steps_per_update == 4.0 and stats.precision == "float32" and stats.final
    assert stats.rejected == {"rejected_batch_shape": 2, "rejected_total": 2, "malformed_stats": 1}
    assert math.isnan(stats.grad_norm) and stats.kappa == 0.0 and stats.start_env_steps is None  # not stated
    assert decode(old("learner", OLD_LEARNER), LearnerStats).updates == 1_200  # where the door expects the type
    assert not decode(old("learner", {**OLD_LEARNER, "final": 0})).final


def test_an_older_actors_stats_decode_into_its_typed_counters():
    stats = decode(old("actor", OLD_ACTOR), ActorStats)
    assert type(stats) is ActorStats and (stats.episodes, stats.episodes_sent, stats.weights_version) == (7, 6, -1)
    assert stats.weights_download_s == 0.0 and stats.weights_behind == 0 and stats.rejected == {"rejected_total": 0}


@pytest.mark.parametrize("source, values, error", [
    ("learner", {**OLD_LEARNER, "updates": "many"}, "LearnerStats.updates: expected an integer, got str"),
    ("learner", {**OLD_LEARNER, "epsilon": float("nan")}, "LearnerStats.epsilon: must be finite"),
    ("learner", {**OLD_LEARNER, "rejected_total": -2}, "LearnerStats.rejected.rejected_total: -2 is outside"),
    ("learner", {**OLD_LEARNER, "final": 2}, "LearnerStats.final: expected a bool, got int"),
    ("learner", {"updates": 5}, r"missing field\(s\) data_wait_share, env_steps, epsilon, loss"),
    ("actor", {**OLD_ACTOR, "episodes": -1}, "ActorStats.episodes: -1 is outside"),
    ("actor", {**OLD_ACTOR, "weights_behind": 1.5}, "ActorStats.weights_behind: expected an integer"),
])
def test_an_older_senders_stats_with_a_value_its_field_refuses_is_a_wire_error(source, values, error):
    with pytest.raises(WireError, match=error):
        decode(old(source, values))


def test_other_untyped_stats_stay_stats_and_are_no_learners_metrics():
    recorder = old("recorder", {"received": 4, "dropped:d3rqn/r/episodes": 1})
    assert type(decode(recorder)) is Stats
    with pytest.raises(WireError, match="expected message type LearnerStats, got Stats") as refused:
        decode(recorder, LearnerStats)
    assert refused.value.kind == "wrong_type"
    with pytest.raises(WireError, match="expected message type ActorStats, got LearnerStats"):
        decode(old("learner", OLD_LEARNER), ActorStats)


def test_a_log_recorded_before_the_typed_metrics_still_reads(tmp_path):
    """An MCAP file with the learner's reports in the old form (its channel typed Stats) beside one in the new:
    both read as LearnerStats, and the run's training curve takes both."""
    config = load_config("smoke")
    key = Keys("d3rqn", config.run.name).metrics_source("learner", "0")
    payloads = [old("learner", OLD_LEARNER), encode(example_learner_stats(updates=1_300, loss_abs_diff=0.003))]
    write_log(tmp_path / "log.mcap", config, key, payloads)
    with LogFile(tmp_path / "log.mcap") as log:
        read = [message for _, message in log.messages(LearnerStats)]
    assert [type(message) for message in read] == [LearnerStats, LearnerStats]
    assert [message.updates for message in read] == [1_200, 1_300]
    curves = read_run_curves([tmp_path / "log.mcap"])
    assert (curves.learner_updates, curves.loss_abs_diffs) == ([1_200.0, 1_300.0], [0.004, 0.003])
