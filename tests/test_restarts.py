"""Any process can die and the run goes on: the local stack SIGKILLed in its replay, its learner or an
actor during training. The stack restarts it, the others ride it out, and the replay's counts show what
was kept (each test prints what it kept, and writes it to kept.json)."""

import json
import os
import signal

from tests.stack_run import StackRun

SNAPSHOT_PERIOD_S = 2.0


def kill(run: StackRun, role: str) -> int:
    pid = run.roles()[role]
    os.kill(pid, signal.SIGKILL)
    return pid


def replaced(run: StackRun, role: str, pid: int):
    return lambda w: run.roles().get(role, pid) != pid


def report(tmp_path, kept: dict) -> None:
    print("\nkept:", json.dumps(kept, indent=1))
    (tmp_path / "kept.json").write_text(json.dumps(kept, indent=1))


def test_a_killed_replay_comes_back_from_its_snapshot_and_training_goes_on(tmp_path):
    with StackRun(tmp_path, "kill-replay", actors=1,
                  flags=("--replay.snapshot_period_s", str(SNAPSHOT_PERIOD_S))) as run:
        # A snapshot that holds episodes, not only written ones: under load the first snapshots can come
        # before any episode does, and a kill then would leave nothing to restore.
        run.wait(lambda w: w.updates() >= 5 and w.replay.get("snapshots_written", 0) >= 2
                 and w.replay.get("snapshot_episodes", 0) >= 5, "training and a snapshot of episodes", timeout_s=80)
        with run.watch.lock:
            last = dict(run.watch.replay)
            updates_at_kill = run.watch.updates()
        pid = kill(run, "replay")
        run.wait(replaced(run, "replay", pid), "a new replay", timeout_s=30)
        run.wait(lambda w: w.replay.get("restored_episodes", 0) > 0, "the restored replay's stats", timeout_s=40)
        with run.watch.lock:
            restored = dict(run.watch.replay)
        run.wait(lambda w: w.updates() >= updates_at_kill + 10, "the learner updating on the restored replay")
        run.wait(lambda w: w.replay["inserted"] >= restored["inserted"] + 3, "the actor's episodes arriving again")
        with run.watch.lock:
            after = dict(run.watch.replay)
        assert run.stop() == 0
    summary = run.summary()
    assert summary["restarts"]["replay"] == 1 and summary["restarts"]["learner"] == 0
    # the snapshot's episodes, at most one period old, came back; the counters carried on
    assert last["snapshot_episodes"] <= restored["restored_episodes"] <= last["episodes"]
    assert restored["restore_skipped"] == 0 and restored["rate_refilling"] == 0
    assert restored["env_steps_total"] >= last["env_steps_total"]  # rate_limiter.json is saved every stats period
    assert restored["rate_batches_served"] >= last["rate_batches_served"] - 5
    assert restored["rate_start_env_steps"] == last["rate_start_env_steps"]
    assert after["episodes_missing"] <= last["inserted"] + last["short_dropped"] + 10  # lost since the snapshot
    # Nothing refused but episodes sent again because the kill cut off the word that a snapshot kept them
    # (actor/delivery.py): the replay refuses those, and stores nothing twice.
    assert after["rejected_total"] == after.get("rejected_episode_duplicate", 0)
    ratio = summary["env_steps_per_update"]
    assert ratio is not None and abs(ratio / 20.0 - 1) < 0.25, summary
    report(tmp_path, {
        "before the kill": {name: last[name] for name in ("episodes", "inserted", "env_steps_total",
                                                          "rate_batches_served", "snapshot_episodes")},
        "snapshot age at the kill (s, as of the last stats)": round(last["snapshot_age_s"], 2),
        "restored": {name: restored[name] for name in ("restored_episodes", "env_steps_total",
                                                       "rate_batches_served", "restore_skipped")},
        "episodes missing (lost with the replay, counted from the actors' indices)": after["episodes_missing"],
        "episodes sent again and refused (kept before the kill, not yet said)": after.get("rejected_episode_duplicate", 0),
        "env steps per update of the run": ratio})


def test_a_killed_learner_resumes_from_its_checkpoint_and_is_owed_what_it_lost(tmp_path):
    with StackRun(tmp_path, "kill-learner", actors=1, flags=("--learner.checkpoint_every", "20")) as run:
        run.wait(lambda w: w.updates() >= 30, "updates past a checkpoint", timeout_s=80)
        with run.watch.lock:
            updates_at_kill = run.watch.updates()
            served_at_kill = run.watch.replay["rate_batches_served"]
        pid = kill(run, "learner")
        run.wait(replaced(run, "learner", pid), "a new learner", timeout_s=30)
        run.wait(lambda w: w.replay.get("rate_lost_updates", 0) > 0, "the replay owing the lost updates", timeout_s=60)
        with run.watch.lock:
            owed = dict(run.watch.replay)
        run.wait(lambda w: w.updates() >= updates_at_kill + 10, "the resumed learner past where it died", timeout_s=60)
        assert run.stop() == 0
    summary = run.summary()
    assert summary["restarts"]["learner"] == 1 and summary["restarts"]["replay"] == 0
    log = (run.run_dir / "logs" / "learner.log").read_text()
    assert "resumed from" in log
    resumed_at = int(log.split("resumed from", 1)[1].split(": ", 1)[1].split(" updates", 1)[0])
    # updates_at_kill is the last count the watch saw; the learner may have passed one more checkpoint before
    # the kill landed (its reports come once a second in the smoke preset), not two.
    assert resumed_at % 20 == 0 and updates_at_kill - 20 - 5 <= resumed_at <= updates_at_kill + 20
    assert owed["rate_lost_updates"] >= served_at_kill - resumed_at - 2  # served then, minus the checkpoint's
    ratio = summary["env_steps_per_update"]
    assert ratio is not None and abs(ratio / 20.0 - 1) < 0.25, summary
    report(tmp_path, {"updates at the kill": updates_at_kill, "batches served at the kill": served_at_kill,
                      "resumed from the checkpoint at": resumed_at,
                      "updates lost and owed again by the replay": owed["rate_lost_updates"],
                      "final updates": summary["updates"], "env steps per update of the run": ratio})


def test_a_killed_actor_is_replaced_and_the_replay_keeps_all_it_stored(tmp_path):
    with StackRun(tmp_path, "kill-actor", actors=2) as run:
        # and the replay's stats (under load its first can come after both actors' third episode)
        run.wait(lambda w: w.updates() >= 3 and all(w.records[a] >= 3 for a in (0, 1)) and w.replay,
                 "both actors and the replay's stats", timeout_s=80)
        with run.watch.lock:
            before = dict(run.watch.replay)
            records = dict(run.watch.records)
        pid = kill(run, "actor-0")
        run.wait(replaced(run, "actor-0", pid), "a new actor 0", timeout_s=30)
        run.wait(lambda w: w.records[0] >= records[0] + 2 and w.records[1] >= records[1] + 2
                 and w.replay["episode_sources"] >= 3, "both actors publishing again, the new one named anew")
        with run.watch.lock:
            after = dict(run.watch.replay)
        assert run.stop() == 0
    assert run.summary()["restarts"]["actor-0"] == 1
    capacity = 50  # the smoke preset's
    assert after["inserted"] > before["inserted"] and after["episodes"] == min(after["inserted"], capacity)
    assert after["evicted"] == max(0, after["inserted"] - capacity)  # nothing lost but by eviction
    assert after["rejected_total"] == 0 and after["episode_sources"] == 3
    report(tmp_path, {"stored before the kill": before["episodes"], "inserted before": before["inserted"],
                      "stored after": after["episodes"], "inserted after": after["inserted"],
                      "evicted": after["evicted"], "actor incarnations seen": after["episode_sources"],
                      "episodes missing": after["episodes_missing"]})


def test_a_stopped_stack_resumes_and_its_actors_drive_only_with_the_learners_policy(tmp_path):
    with StackRun(tmp_path, "resume", actors=1) as run:
        run.wait(lambda w: w.updates() >= 5, "updates under way", timeout_s=90)
        assert run.stop() == 0
    first = run.summary()
    first_updates = first["updates"]
    with StackRun(tmp_path, "resume", actors=1, flags=("--resume",)) as resumed:
        resumed.wait(lambda w: w.updates() >= first_updates + 5 and len(w.episodes) >= 5,
                     "the resumed learner and actor at work", timeout_s=120)
        assert resumed.stop() == 0
        with resumed.watch.lock:
            versions = [int(step) for episode in resumed.watch.episodes.values() for step in episode.weights_version]
    # updates had started before the stop, so no step after the resume may be driven without the learner's
    # weights (version -1: uniform random actions) while the learner loads its checkpoint
    assert versions and min(versions) >= 0, sorted(versions)[:20]
    after = resumed.summary()
    assert after["updates"] > first_updates
    # the run's episode total carries on from the first stack's, not from 0
    assert first["replay_episodes_total"] > 0
    assert after["replay_episodes_total"] > max(first["replay_episodes_total"], after["episodes"])
    report(tmp_path, {"updates before the stop": first_updates, "steps seen after the resume": len(versions),
                      "lowest weights version after the resume": min(versions)})
