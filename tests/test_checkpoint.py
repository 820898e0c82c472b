"""The learner's checkpoint read back by name: round trip, and one clear error for a damaged or partial file."""

import pytest
import torch

from common.checkpoint import Checkpoint, CheckpointError, save_checkpoint
from common.config_values import load_config, to_dict
from common.run_dir import RunDir
from learner.update import DoubleQLearner


@pytest.fixture
def run(tmp_path):
    return RunDir(tmp_path / "bmc")


def saved(run: RunDir) -> tuple[DoubleQLearner, Checkpoint]:
    config = load_config("smoke", overrides={"network.lstm_units": 16})
    learner = DoubleQLearner(config.network, config.learner)
    learner.updates = 12
    checkpoint = Checkpoint(learner=learner.state_dict(), exploration={"strategy": "bmc"},
                            clock={"env_steps": 3400, "start_env_steps": 100.0}, config=to_dict(config))
    assert checkpoint.save(run.checkpoints) == run.checkpoint
    return learner, checkpoint


def test_a_checkpoint_reads_back_by_name_from_its_file_its_folder_or_its_run(run):
    learner, _ = saved(run)
    for path in (run.checkpoint, run.checkpoints, run.root):
        checkpoint = Checkpoint.load(path, complete=True)
        assert checkpoint.path == run.checkpoint
        assert (checkpoint.env_steps, checkpoint.updates) == (3400, 12)
        assert checkpoint.exploration == {"strategy": "bmc"}
        assert checkpoint.config["network"]["lstm_units"] == 16
    weights = checkpoint.policy_weights()
    online = learner.online.state_dict()
    assert sorted(weights) == sorted(online)
    assert all(torch.equal(torch.from_numpy(weights[name]), tensor) for name, tensor in online.items())
    assert not list(run.checkpoints.glob("*.tmp"))


@pytest.mark.parametrize("damage, message", [
    (lambda data: data[:len(data) // 2], "cannot read checkpoint"),  # truncated
    (lambda data: b"not a checkpoint", "cannot read checkpoint"),
])
def test_a_damaged_checkpoint_is_one_clear_error(run, damage, message):
    saved(run)
    run.checkpoint.write_bytes(damage(run.checkpoint.read_bytes()))
    with pytest.raises(CheckpointError, match=message):
        Checkpoint.load(run.root)


def test_a_file_that_is_not_a_checkpoint_or_no_file_is_a_checkpoint_error(run):
    with pytest.raises(CheckpointError, match="no checkpoint at"):
        Checkpoint.load(run.root)
    run.checkpoints.mkdir(parents=True)
    torch.save([1, 2, 3], run.checkpoint)
    with pytest.raises(CheckpointError, match="is not a d3rqn checkpoint"):
        Checkpoint.load(run.checkpoint)


def test_a_partial_checkpoint_says_what_it_lacks(run):
    save_checkpoint(run.checkpoints, {"clock": {"env_steps": 50}, "learner": {"updates": 2}})
    with pytest.raises(CheckpointError, match="lacks exploration, config"):
        Checkpoint.load(run.root, complete=True)
    checkpoint = Checkpoint.load(run.root)
    assert (checkpoint.env_steps, checkpoint.updates) == (50, 2)
    with pytest.raises(CheckpointError, match="lacks its config section"):
        checkpoint.config
    with pytest.raises(CheckpointError, match="no online network"):
        checkpoint.policy_weights()
    save_checkpoint(run.checkpoints, {"config": {}})
    assert Checkpoint.load(run.root).env_steps is None and Checkpoint.load(run.root).updates is None


@pytest.mark.parametrize("payload, message", [
    ({"clock": {"env_steps": "many"}}, "clock env_steps 'many' is not a count"),
    ({"clock": {"env_steps": -1}}, "is not a count"),
    ({"clock": [1, 2]}, "has a malformed clock section"),
])
def test_a_malformed_count_is_a_checkpoint_error(run, payload, message):
    save_checkpoint(run.checkpoints, payload)
    with pytest.raises(CheckpointError, match=message):
        Checkpoint.load(run.root).env_steps
