"""Random-shift augmentation (learner.shift_pad, beyond the paper; learner/frame_shift.py): the shift by hand,
one offset per trace, the same frames for the online and target passes, and off leaves the update as it was."""

import dataclasses
import itertools

import numpy as np
import pytest
import torch

from common.config import LearnerConfig
from common.config_values import load_config
from common.schema.fields import ConfigError
from learner.frame_shift import draw_offsets, shift_frames
from learner.update import DoubleQLearner
from tests.test_update import TINY, flat_parameters, one_torch_thread, random_batch  # noqa: F401 (a fixture)

PAD = 4
SHIFTED = dataclasses.replace(LearnerConfig(), shift_pad=PAD, update_path="trace")  # no timing of paths


def test_the_shift_is_the_hand_computed_one():
    frames = torch.arange(12, dtype=torch.uint8).reshape(1, 1, 3, 4, 1)  # rows 0-3, 4-7, 8-11
    shifted = shift_frames(frames, torch.tensor([[1, -2]]))  # one row down the image, two columns left of it
    # rows 1, 2, 2 (the last repeated) of columns 0, 0, 0, 1 (the first repeated)
    assert shifted[0, 0, :, :, 0].tolist() == [[4, 4, 4, 5], [8, 8, 8, 9], [8, 8, 8, 9]]


def test_the_shift_is_an_edge_padded_crop():
    """DrQ's form: pad by PAD repeating the edge (numpy's "edge" pad), crop at (PAD + dy, PAD + dx)."""
    rng = np.random.default_rng(0)
    frames = rng.integers(0, 256, (2, 3, 7, 9, 3), dtype=np.uint8)
    padded = np.pad(frames, ((0, 0), (0, 0), (PAD, PAD), (PAD, PAD), (0, 0)), mode="edge")
    for dy, dx in [(-PAD, PAD), (0, 0), (3, -1), (PAD, -PAD)]:
        crop = padded[:, :, PAD + dy:PAD + dy + 7, PAD + dx:PAD + dx + 9]
        shifted = shift_frames(torch.from_numpy(frames), torch.tensor([[dy, dx], [dy, dx]]))
        assert np.array_equal(shifted.numpy(), crop), (dy, dx)


def test_offsets_lie_within_the_pad_and_follow_the_seed():
    offsets = draw_offsets(torch.Generator().manual_seed(3), 1000, PAD)
    assert offsets.shape == (1000, 2) and offsets.min() == -PAD and offsets.max() == PAD
    assert torch.equal(offsets, draw_offsets(torch.Generator().manual_seed(3), 1000, PAD))


def seen_frames(learner: DoubleQLearner) -> dict[str, list[torch.Tensor]]:
    """Records the frames each network's passes read, as uint8 (B, T + 1, h, w, C), whatever the update path."""
    seen = {"online": [], "target": []}
    for name in seen:
        network = getattr(learner, name)
        trace_q_values, forward = network.trace_q_values, network.forward

        def traced(pixels, traces, *args, name=name, trace_q_values=trace_q_values, **kwargs):
            steps = pixels.shape[0] // traces
            frames = pixels.permute(0, 2, 3, 1).reshape(steps, traces, *pixels.shape[2:], pixels.shape[1])
            seen[name].append(torch.round(frames.transpose(0, 1) * 255).to(torch.uint8))
            return trace_q_values(pixels, traces, *args, **kwargs)

        def forwarded(observations, *args, name=name, forward=forward, network=network, **kwargs):
            seen[name].append(observations[:, :, :network.used_frame_size[0], :network.used_frame_size[1]])
            return forward(observations, *args, **kwargs)

        network.trace_q_values, network.forward = traced, forwarded
    return seen


def offsets_of(seen: torch.Tensor, observations: np.ndarray, network) -> np.ndarray:
    """The offset each (trace, step) of `seen` was shifted by: int (B, T + 1, 2), found among every offset within
    the pad (random frames match one only)."""
    frames = torch.from_numpy(observations)
    height, width = network.used_frame_size
    found = np.full((*seen.shape[:2], 2), 99)
    for dy, dx in itertools.product(range(-PAD, PAD + 1), repeat=2):
        candidate = shift_frames(frames, torch.tensor([[dy, dx]] * len(frames)))[:, :, :height, :width]
        match = (candidate == seen).flatten(2).all(-1).numpy()
        found[match] = (dy, dx)
    assert (found != 99).all(), "a frame the network read is no shift of the batch's"
    return found


def one_shifted_update(path: str):
    """A learner after one update with the shifts on, the frames its networks read, and the batch."""
    learner = DoubleQLearner(TINY, dataclasses.replace(SHIFTED, update_path=path))
    seen = seen_frames(learner)
    batch = random_batch(np.random.default_rng(0))
    learner.update(batch)
    return learner, seen, batch


@pytest.mark.parametrize("path", ["trace", "trace-split", "autograd"])
def test_every_step_of_a_trace_has_one_offset_and_traces_differ(path):
    learner, seen, batch = one_shifted_update(path)
    offsets = offsets_of(seen["online"][0], batch.observations, learner.online)
    assert (offsets == offsets[:, :1]).all(), "the steps of a trace were shifted by different offsets"
    assert len({tuple(trace[0]) for trace in offsets}) > 1, "every trace was shifted alike"
    assert not (offsets == 0).all()


@pytest.mark.parametrize("path", ["trace", "trace-split", "autograd"])
def test_the_online_and_target_passes_read_the_same_shifted_frames(path):
    learner, seen, batch = one_shifted_update(path)
    (online,), (target,) = seen["online"], seen["target"]
    height, width = learner.online.used_frame_size
    assert not torch.equal(online, torch.from_numpy(batch.observations[:, :, :height, :width]))  # shifted
    assert torch.equal(online, target)


def updated(learner: DoubleQLearner, count: int = 3) -> list[float]:
    rng = np.random.default_rng(2)
    return [learner.update(random_batch(rng), with_q_after=True).loss for _ in range(count)]


def without_shifts(learner: DoubleQLearner) -> DoubleQLearner:
    learner.shifted = lambda tensors: tensors  # the update as it was before the option
    return learner


@pytest.mark.parametrize("path", ["trace", "autograd"])
def test_off_the_update_is_bit_identical_to_the_one_without_shifts(path):
    config = dataclasses.replace(LearnerConfig(), update_path=path)
    plain, off = without_shifts(DoubleQLearner(TINY, config)), DoubleQLearner(TINY, config)
    assert updated(off) == updated(plain)
    assert torch.equal(flat_parameters(off.online), flat_parameters(plain.online))
    assert torch.equal(flat_parameters(off.target), flat_parameters(plain.target))
    assert "shifts" not in off.state_dict()
    shifted = DoubleQLearner(TINY, dataclasses.replace(SHIFTED, update_path=path))
    assert updated(shifted) != updated(without_shifts(DoubleQLearner(TINY, config)))  # the check can see a shift


def test_a_resumed_learner_draws_the_shifts_an_unbroken_one_draws():
    unbroken, first = DoubleQLearner(TINY, SHIFTED), DoubleQLearner(TINY, SHIFTED)
    losses = updated(unbroken, 4)
    rng = np.random.default_rng(2)
    batches = [random_batch(rng) for _ in range(4)]
    for batch in batches[:2]:
        first.update(batch, with_q_after=True)
    resumed = DoubleQLearner(TINY, SHIFTED)
    resumed.load_state_dict(first.state_dict())
    assert [resumed.update(batch, with_q_after=True).loss for batch in batches[2:]] == losses[2:]


def test_a_negative_pad_is_refused():
    with pytest.raises(ConfigError, match="shift_pad: must be >= 0 pixels"):
        dataclasses.replace(LearnerConfig(), shift_pad=-1).validate()
    with pytest.raises(ConfigError, match="learner.shift_pad"):
        load_config("paper", overrides={"learner.shift_pad": -4})
