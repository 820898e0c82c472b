"""Checkpoint and --resume: an interrupted learner continues exactly where it stopped."""

import numpy as np
import pytest
import torch

from common.checkpoint import SECTIONS as CHECKPOINT_SECTIONS, CheckpointError, load_checkpoint
from common.config_values import load_config
from common.schema.fields import ConfigError
from common.wire.frames import FrameStack
from common.wire.messages import TraceBatch
from learner.service import LearnerService
from tests.test_status_lines import FakeClock
from wire_examples import example_rate, example_replay_stats

SIZE, STEPS, TRACES = 36, 4, 3


@pytest.fixture
def config(tmp_path):
    return load_config("smoke", overrides={
        "network.frame_height": SIZE, "network.frame_width": SIZE, "network.lstm_units": 16,
        "learner.trace_length": STEPS, "learner.n_mask": 2, "learner.batch_size": TRACES,
        "learner.lr": 1e-3, "exploration.strategy": "bmc", "run.runs_dir": str(tmp_path)})


def batches(count: int) -> list[TraceBatch]:
    rng = np.random.default_rng(0)
    made = []
    for index in range(count):
        frames = rng.integers(0, 256, size=(TRACES * (STEPS + 1), SIZE, SIZE, 3), dtype=np.uint8)
        made.append(TraceBatch(
            request_id=index, observations=FrameStack.from_array(frames),
            actions=rng.integers(0, 5, size=(TRACES, STEPS)), rewards=rng.random((TRACES, STEPS), dtype=np.float32),
            terminated=np.zeros((TRACES, STEPS), bool), weights_version=np.zeros((TRACES, STEPS), np.int64),
            env_steps_total=100 + 40 * index, episodes_stored=10))
    return made


def train(service: LearnerService, batch: TraceBatch) -> None:
    """As in the process: the replay's stats move the clock, then the batch is trained on."""
    rate = example_rate(env_steps=batch.env_steps_total, start_env_steps=None, batches_served=0)
    service.on_replay_stats(example_replay_stats(rate, episodes=batch.episodes_stored))
    service.train_on(batch)


def started(config) -> LearnerService:
    service = LearnerService(config)
    service.start_updates()
    return service


@pytest.mark.parametrize("shift_pad", [0, 4])  # 4: the random shifts' generator is checkpointed too
def test_resume_continues_as_if_never_stopped(config, shift_pad):
    config.learner.shift_pad = shift_pad
    data = batches(6)
    uninterrupted = started(config)
    for batch in data:
        train(uninterrupted, batch)

    first = started(config)
    for batch in data[:3]:
        train(first, batch)
    first.checkpoint()
    resumed = LearnerService(config)
    resumed.resume()
    assert resumed.updates == 3 and resumed.strategy.started
    for batch in data[3:]:
        train(resumed, batch)

    for name, tensor in uninterrupted.learner.state_dict()["online"].items():
        assert torch.equal(tensor, resumed.learner.state_dict()["online"][name]), name
    for name, tensor in uninterrupted.learner.state_dict()["target"].items():
        assert torch.equal(tensor, resumed.learner.state_dict()["target"][name]), name
    assert resumed.strategy.state_dict() == uninterrupted.strategy.state_dict()
    assert resumed.clock.env_steps == uninterrupted.clock.env_steps


def test_checkpoint_is_written_atomically_with_every_section(config):
    process = started(config)
    train(process, batches(1)[0])
    path = process.checkpoint()
    assert path.name == "latest.pt" and not list(path.parent.glob("*.tmp"))
    payload = load_checkpoint(path.parent, CHECKPOINT_SECTIONS)
    assert payload["config"]["learner"]["trace_length"] == STEPS


def test_damaged_or_missing_checkpoint_is_a_clear_error(config, tmp_path):
    with pytest.raises(CheckpointError, match="no checkpoint"):
        LearnerService(config).resume()
    process = started(config)
    path = process.checkpoint()
    path.write_bytes(path.read_bytes()[:1000])
    with pytest.raises(CheckpointError, match="cannot read checkpoint"):
        LearnerService(config).resume()


def test_the_learner_checkpoints_every_n_updates_or_every_period_by_its_clock(config):
    clock = FakeClock()
    config.learner.checkpoint_every, config.learner.checkpoint_every_s = 5, 10.0
    service = LearnerService(config, clock=clock)
    service.start_updates()
    written = []
    for batch in batches(10):
        clock.now += 3.0  # an update takes 3 s
        train(service, batch)
        service.checkpoint_if_due()
        if service.checkpoint_dir.joinpath("latest.pt").exists():
            updates = load_checkpoint(service.checkpoint_dir, CHECKPOINT_SECTIONS)["learner"]["updates"]
            written += [] if written and written[-1] == updates else [updates]
    # 12 s at update 4 (by time), the 5th (by count), 27 s at update 9 (12 s after 15 s), the 10th
    assert written == [4, 5, 9, 10]


def test_checkpoint_period_must_not_be_negative():
    with pytest.raises(ConfigError, match="learner.checkpoint_every_s"):
        load_config("paper", overrides={"learner.checkpoint_every_s": -1})
