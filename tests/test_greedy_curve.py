"""Greedy learning curves: the learner keeps policies at its cadence, and a kept file reads back into the
network."""

import math
import time

import pytest
import torch

from common.checkpoint import CheckpointError, KeptPolicy
from common.config import ConfigError, from_dict, load_config
from common.network import D3RQN, load_numpy_weights
from common.run_dir import RunDir
from deploy.experiments import keep_flags
from learner.service import LearnerProcess
from tests.test_learner_resume import batches, config, train  # noqa: F401 (config: a fixture)
from tests.test_progress import FakeClock


def learner(config, clock=time.monotonic, keep_every=0, keep_every_s=0.0) -> LearnerProcess:
    config.learner.keep_every, config.learner.keep_every_s = keep_every, keep_every_s
    process = LearnerProcess(config, clock=clock)
    process.start_updates()
    return process


def kept(config) -> list[int]:
    return [updates for updates, _ in RunDir.of(config).kept_policies()]


# --- the learner keeps policies ----------------------------------------------------------------------------

def test_the_learner_keeps_a_policy_every_n_updates_and_at_the_end(config):
    process = learner(config, keep_every=2)
    for batch in batches(5):
        train(process, batch)
        process.keep_policy_if_due()
    process.keeper.wait()
    assert kept(config) == [2, 4]
    process.keep_last_policy()
    assert kept(config) == [2, 4, 5]
    run = RunDir.of(config)
    assert [path.name for _, path in run.kept_policies()] == ["policy-u0000002.pt", "policy-u0000004.pt",
                                                             "policy-u0000005.pt"]
    assert not list(run.policies.glob(".*"))  # written whole: no temporary file left behind
    second = KeptPolicy.load(run.policy(2))
    assert (second.updates, second.env_steps) == (2, 140)  # the replay's count after the second batch
    assert second.config["learner"]["keep_every"] == 2


def test_the_learner_keeps_a_policy_every_period_by_its_clock(config):
    clock = FakeClock()
    process = learner(config, clock, keep_every_s=10.0)
    for batch in batches(6):
        clock.now += 4.0  # an update takes 4 s
        train(process, batch)
        process.keep_policy_if_due()
    process.keep_last_policy()  # the last one was just kept: not again
    run = RunDir.of(config)
    assert kept(config) == [3, 6]
    assert [KeptPolicy.load(path).wall_s for _, path in run.kept_policies()] == [12.0, 24.0]


def test_without_a_cadence_nothing_is_kept(config):
    process = learner(config)
    for batch in batches(2):
        train(process, batch)
        process.keep_policy_if_due()
    process.keep_last_policy()
    assert kept(config) == []


def test_a_resumed_run_s_wall_time_carries_on(config):
    clock = FakeClock()
    first = learner(config, clock, keep_every=1)
    train(first, batches(1)[0])
    clock.now += 100.0
    first.checkpoint()
    later = FakeClock()
    later.now = 5000.0  # another session: its clock has its own origin
    resumed = LearnerProcess(config, clock=later)
    resumed.resume()
    later.now += 30.0
    train(resumed, batches(2)[1])
    resumed.keep_policy_if_due()
    resumed.keeper.wait()
    assert KeptPolicy.load(RunDir.of(config).policy(2)).wall_s == pytest.approx(130.0)


# --- the kept file ---------------------------------------------------------------------------------------------

def test_a_kept_policy_reads_back_into_the_network(config):
    process = learner(config, keep_every=1)
    train(process, batches(1)[0])
    process.keep_policy_if_due()
    process.keeper.wait()
    path = RunDir.of(config).policy(1)
    payload = torch.load(path, weights_only=True)
    assert set(payload) == {"format", "updates", "env_steps", "wall_s", "cpu", "config", "online"}  # no target
    policy = KeptPolicy.load(path)
    network = D3RQN(from_dict(policy.config).network)
    load_numpy_weights(network, policy.weights())
    shape = (1, 2, config.network.frame_height, config.network.frame_width, 3)
    frames = torch.randint(0, 256, shape, dtype=torch.uint8)
    with torch.no_grad():
        assert torch.equal(network(frames)[0], process.learner.online(frames)[0])


def test_a_damaged_or_foreign_policy_file_is_a_clear_error(config, tmp_path):
    process = learner(config, keep_every=1)
    train(process, batches(1)[0])
    process.keep_policy_if_due()
    process.keeper.wait()
    path = RunDir.of(config).policy(1)
    good = path.read_bytes()
    path.write_bytes(good[:len(good) // 2])
    with pytest.raises(CheckpointError, match="cannot read kept policy"):
        KeptPolicy.load(path)
    checkpoint = process.checkpoint()
    with pytest.raises(CheckpointError, match="is not a kept policy"):
        KeptPolicy.load(checkpoint)
    payload = torch.load(checkpoint, weights_only=True)
    torch.save({"format": "d3rqn kept policy", "updates": -1, "env_steps": 3, "wall_s": math.nan, "cpu": "x",
                "config": payload["config"], "online": payload["learner"]["online"]}, path)
    with pytest.raises(CheckpointError, match="updates, wall_s missing or malformed"):
        KeptPolicy.load(path)


def test_keeping_options_are_checked_and_set_by_the_presets_and_the_grid():
    assert (load_config("paper").learner.keep_every, load_config("paper").learner.keep_every_s) == (0, 0.0)
    assert load_config("local").learner.keep_every == 1_000 and load_config("smoke").learner.keep_every == 100
    with pytest.raises(ConfigError, match="learner.keep_every_s"):
        load_config("paper", overrides={"learner.keep_every_s": -1})
    # the grid: a config that keeps nothing keeps about 20 policies a run; one that keeps is left alone
    assert keep_flags(["--preset", "paper"], 80_000) == ["--learner.keep_every", "1000"]
    assert keep_flags(["--preset", "local"], 80_000) == []
    assert keep_flags(["--learner.keep_every_s", "60"], 80_000) == []
