"""A live stack flooded on every key and queryable of its run with hostile input: random bytes,
truncated and bit-flipped messages, valid messages of the wrong type, and well-formed messages that do
not fit the run. Afterwards every process is the one that was there before, the replay stores only
episodes that fit (its snapshot holds nothing else), the learner keeps updating, the actors keep
publishing, and each refusal is counted by kind in the stats of the role that refused it."""

import json
import time

import numpy as np
import zenoh

from common.config_values import load_config
from common.wire.envelope import decode, encode
from common.wire.errors import WireError
from common.wire.messages import (Episode, EpisodeAck, ExplorationState, RateState, ReplayStats, Stats,
                                  TraceBatchRequest, Weights)
from common.wire.metrics import ActorStats, LearnerStats
from common.wire.run_shape import RunShape, check_episode
from replay.snapshot import Snapshotter
from tests import hostile
from tests.stack_run import SMALL, StackRun, episode_digest

RUN = "flood"
PER_KIND = 100  # random payloads, truncations and bit flips per key
FLOOD_FLAGS = ("--actors", "2", "--replay.snapshot_period_s", "2")


def run_config(tmp_path):
    flags = dict(zip(SMALL[2::2], SMALL[3::2]))
    return load_config("smoke", overrides={key.lstrip("-"): value for key, value in flags.items()})


def test_a_flood_of_hostile_input_stops_nothing(tmp_path):
    config = run_config(tmp_path)
    shape = RunShape.of(config)
    rng = np.random.default_rng(12)
    with StackRun(tmp_path, RUN, actors=2, flags=("--replay.snapshot_period_s", "2")) as run:
        run.wait(lambda w: w.updates() >= 3 and all(w.records[a] >= 2 for a in (0, 1)) and w.actor_stats
                 and w.episodes and w.replay.get("snapshots_written", 0) >= 1,
                 "training, both actors and a snapshot", timeout_s=80)
        before = run.roles()
        assert sorted(before) == ["actor-0", "actor-1", "learner", "recorder", "replay"], before
        with run.watch.lock:
            updates_before, records_before = run.watch.updates(), dict(run.watch.records)
            inserted_before = run.watch.replay["inserted"]
            genuine = next(iter(run.watch.episodes.values()))

        sent, accepted, refused, took = flood(run, config, shape, rng, genuine)

        run.wait(lambda w: w.updates() >= updates_before + 10, "the learner updating after the flood")
        run.wait(lambda w: all(w.records[a] >= records_before[a] + 2 for a in (0, 1))
                 and w.replay["inserted"] >= inserted_before + 4, "both actors publishing after the flood")
        time.sleep(2.0)  # a last round of stats from everyone
        assert run.roles() == before, "a process of the stack died and was restarted"
        with run.watch.lock:
            replay, learner = dict(run.watch.replay), dict(run.watch.learner)
            actors = {key: dict(values) for key, values in run.watch.actor_stats.items()}
        totals = {"messages": sum(n for door in sent.values() for name, n in door.items() if name != "bytes"),
                  "bytes": sum(door["bytes"] for door in sent.values())}
        report = {"sent": sent, "total": totals, "seconds": took, "replay": rejected(replay), "learner": rejected(learner),
                  **{f"actor-{key}": rejected(values) for key, values in sorted(actors.items())}}
        print("\nflood report:", json.dumps(report, indent=1))
        (tmp_path / "flood_report.json").write_text(json.dumps(report, indent=1))
        check_refusals(replay, learner, actors, sent)
        assert run.stop() == 0
        # read after the stop: the actors publish until they are stopped, and the last snapshot keeps that too
        with run.watch.lock:
            heard = dict(run.watch.episodes)  # digest -> episode
    assert run.summary()["restarts"] == dict.fromkeys(("replay", "recorder", "learner", "actor-0", "actor-1"), 0)
    # the replay's final snapshot: no flooded episode that does not fit, no episode twice, every one whole
    restored = Snapshotter(run.run_dir / "replay" / "snapshot").load(shape.frame_shape)
    assert restored.skipped == 0 and len(restored.episodes) >= replay["episodes"] > 0
    digests = [episode_digest(stored.frames.blobs, stored.actions, stored.rewards) for stored in restored.episodes]
    assert len(set(digests)) == len(digests) and not set(digests) & refused
    # each actor numbers its episodes from 0, so the lowest index heard counts those it sent before we listened
    unheard = sum(min((e.episode_index for e in heard.values() if e.actor_id == actor), default=0) for actor in (0, 1))
    in_flight = 2  # sent as the router closed: stored by the replay, perhaps not forwarded to us
    assert len(set(digests) & set(heard)) >= len(digests) - len(accepted) - unheard - in_flight
    for stored in restored.episodes:
        stored.frames.verify()
        assert 0 <= stored.actions.min() and stored.actions.max() < shape.n_actions
        assert np.abs(stored.rewards).max() <= shape.reward_limit


def flood(run: StackRun, config, shape: RunShape, rng, genuine: Episode) -> tuple[dict, set, set, float]:
    """Floods every key and queryable; returns what was sent by door, the digests of the flooded episodes
    that decode and fit the run (bit flips that leave a valid episode: indistinguishable from a real one)
    and of those that decode but do not fit, and the seconds it took."""
    keys, session = run.keys, run.session
    examples = hostile.examples(config)
    doors = {  # key -> the message type that belongs there
        keys.episodes: Episode, keys.replay_stats: ReplayStats, keys.replay_rate: RateState, keys.weights: Weights,
        keys.exploration: ExplorationState, keys.metrics_source("learner", "0"): LearnerStats,
        keys.metrics_source("actor", "0"): Stats, keys.metrics_source("actor_stats", "1"): ActorStats,
        keys.metrics_source("recorder", "0"): Stats,
        keys.replay_sample: TraceBatchRequest, keys.weights_latest: TraceBatchRequest,
        keys.episode_acks(0): EpisodeAck, keys.episode_acks(1): EpisodeAck,
    }
    misfits = {keys.episodes: hostile.misfit_episodes(config), keys.weights: hostile.misfit_weights(config),
               keys.exploration: hostile.misfit_exploration(config)}
    for key in (keys.metrics_source("learner", "0"), keys.metrics_source("actor_stats", "1")):
        misfits[key] = hostile.misfit_stats()
    for key in (keys.replay_stats, keys.replay_rate):
        misfits[key] = {**hostile.misfit_stats(), **hostile.misfit_replay_word()}
    for actor in (0, 1):  # a well-formed word on episodes that are not this actor's
        misfits[keys.episode_acks(actor)] = {"foreign": encode(examples[EpisodeAck])}
    sent: dict[str, dict[str, int]] = {}
    accepted: set[str] = set()
    refused: set[str] = set()
    started = time.monotonic()
    for key, right in doors.items():
        base = encode(examples[right])
        payloads = {"random": hostile.random_payloads(rng, PER_KIND), "truncated": hostile.truncations(base, rng, PER_KIND),
                    "bit_flips": hostile.bit_flips(base, rng, PER_KIND), "wrong_type": hostile.wrong_types(config, right),
                    **{name: [data] for name, data in misfits.get(key, {}).items()}}
        if key == keys.episodes:
            payloads["duplicate"] = [encode(genuine)]  # a real episode again, as a log played into the run
            for name, items in payloads.items():
                for data in items:
                    verdict, digest = _verdict(data, shape)
                    if verdict == "fits" and name == "bit_flips":
                        accepted.add(digest)
                    elif verdict == "misfit":
                        refused.add(digest)
        if key == keys.replay_sample:
            payloads["wrong_size"] = [encode(TraceBatchRequest(request_id=n, batch_size=size, trace_length=length))
                                      for n, (size, length) in enumerate([(2, 3), (10**6, 5), (2, 10**6)])]
        door = key[len(keys.root) + 1:]
        sent[door] = {name: len(items) for name, items in payloads.items()}
        sent[door]["bytes"] = sum(len(data) for items in payloads.values() for data in items)
        if right is TraceBatchRequest:  # a queryable: ask it, and put on its key too
            for items in payloads.values():
                for data in items:
                    for reply in session.get(key, payload=data, timeout=2.0):
                        pass
        publisher = session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
        for items in payloads.values():
            for data in items:
                publisher.put(data)
        publisher.undeclare()
    for key in (keys.episodes, keys.replay_stats):  # queries where nothing answers
        for data in hostile.random_payloads(rng, 5):
            for reply in session.get(key, payload=data, timeout=0.5):
                pass
    return sent, accepted, refused, time.monotonic() - started


def _verdict(data: bytes, shape: RunShape) -> tuple[str, str | None]:
    """("malformed", None), ("misfit", digest) or ("fits", digest) for an episode payload."""
    try:
        episode = decode(data, Episode)
    except WireError:
        return "malformed", None
    digest = episode_digest(episode.observations.blobs, episode.actions, episode.rewards)
    try:
        check_episode(episode, shape)
    except WireError:
        return "misfit", digest
    return "fits", digest


def rejected(values: dict) -> dict:
    return {name: count for name, count in values.items()
            if (name.startswith(("rejected_", "malformed_")) or name in ("failed_updates", "failed_samples"))
            and count}


def check_refusals(replay: dict, learner: dict, actors: dict, sent: dict) -> None:
    """Each door counted what it refused, by kind (at least what was sure to be refused: bit flips and
    the actors' newest-only mailboxes make some counts lower bounds)."""
    junk = PER_KIND * 2  # random payloads and truncations never decode
    assert replay["malformed_episodes"] >= junk and replay["rejected_episode_wrong_type"] >= 7
    for kind in ("frame_shape", "frames_corrupt", "actions", "rewards", "length", "weights_version", "duplicate"):
        assert replay.get(f"rejected_episode_{kind}", 0) >= 1, kind
    assert replay["malformed_requests"] >= junk and replay["rejected_request_wrong_type"] >= 7
    assert replay["rejected_request_size"] >= 3  # a state naming no strategy the wire refuses: malformed
    assert replay["malformed_exploration"] >= junk and replay["failed_samples"] == 0
    assert learner["malformed_stats"] >= junk and learner["malformed_rate"] >= junk
    assert learner["rejected_stats_wrong_type"] >= 7 and learner["rejected_rate_wrong_type"] >= 7
    assert learner["rejected_stats_values"] >= 1 and learner["rejected_rate_values"] >= 1  # the absurd counts
    assert learner["rejected_weights_query"] >= 7 and learner["malformed_weights_query"] >= PER_KIND
    assert learner["failed_updates"] == 0 and learner.get("rejected_total", 0) >= 40
    for values in actors.values():
        assert values["malformed_weights"] >= junk + 1  # + the non-finite weights the wire refuses
        assert values["rejected_weights_network"] >= 3 and values["rejected_weights_wrong_type"] >= 7
        assert values["rejected_rate"] >= 7 and values["malformed_rate"] >= junk
        assert values["rejected_rate_values"] >= 1
        assert values["malformed_exploration"] >= junk and values["rejected_exploration_wrong_type"] >= 1
        assert values["malformed_acks"] >= junk + 7 and values["acks_foreign"] >= 1  # words on others' episodes
        assert values["episodes_released"] == 0 and values["episodes_kept"] >= 1
