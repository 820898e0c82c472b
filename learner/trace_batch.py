"""The traces of a learner step, as the replay sends them (TraceArrays) and on the learner's device
(TraceTensors): the one check of their sizes against the run (checked_arrays), and their staging ahead
of the update (BatchStager, from the prefetcher's threads; on CUDA through page-locked buffers).
"""

from __future__ import annotations

import dataclasses
import threading
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import torch

from common.config import LearnerConfig, NetworkConfig
from common.trace_pass import scale_frames

if TYPE_CHECKING:
    from learner.update import DoubleQLearner


@dataclass(frozen=True)
class TraceArrays:
    """B sampled traces as numpy arrays (what the replay sends)."""

    observations: np.ndarray  # uint8 (B, T + 1, height, width, channels): s_0..s_T
    actions: np.ndarray  # integers (B, T): a_t taken in s_t
    rewards: np.ndarray  # floats (B, T): r_t received after a_t
    terminated: np.ndarray  # bools (B, T): s_t+1 is terminal (a time-limit cut is not)
    initial_state: np.ndarray | None = None  # floats (B, 2, lstm_units): (h, c) before s_0 (learner.stored_state)

    @classmethod
    def from_batch(cls, batch, observations: np.ndarray | None = None) -> "TraceArrays":
        """The arrays of a TraceBatch message (common/wire/messages.py); its frames decoded unless given."""
        rows = np.asarray(batch.initial_state)
        observations = batch.observations_array() if observations is None else observations
        return cls(observations, np.array(batch.actions), np.array(batch.rewards), np.array(batch.terminated),
                   rows if rows.size else None)


@dataclass(frozen=True)
class TraceTensors:
    """The traces of a TraceArrays on the learner's device."""

    observations: torch.Tensor  # uint8 (B, T + 1, H, W, C)
    actions: torch.Tensor  # int64 (B, T)
    rewards: torch.Tensor  # float32 (B, T)
    terminated: torch.Tensor  # float32 (B, T), 1.0 where terminal
    initial_state: torch.Tensor | None = None  # float32 (B, 2, lstm_units), or None: the zero state
    # Prepared ahead by DoubleQLearner.stage: the frames as the trace passes read them
    # (scale_frames(observations, used_frame_size)), and the CUDA event the copies end with.
    pixels: torch.Tensor | None = None
    ready: object | None = None



def to_tensors(batch: TraceArrays, network: NetworkConfig, learner: LearnerConfig,
               device: torch.device) -> TraceTensors:
    """Checks a batch against the configured sizes (ValueError naming the field) and moves it to device."""
    return _on_device(checked_arrays(batch, network, learner), device)


def _on_device(arrays: tuple[np.ndarray | None, ...], device: torch.device) -> TraceTensors:
    observations, actions, rewards, terminated, initial_state = arrays
    return TraceTensors(
        observations=torch.from_numpy(observations).to(device),
        actions=torch.as_tensor(actions, dtype=torch.int64, device=device),
        rewards=torch.as_tensor(rewards, dtype=torch.float32, device=device),
        terminated=torch.as_tensor(terminated, dtype=torch.float32, device=device),
        initial_state=_state_on(initial_state, device),
    )


def _state_on(initial_state: np.ndarray | None, device: torch.device) -> torch.Tensor | None:
    if initial_state is None:
        return None
    # a copy: the stored state arrives as a read-only view of the wire's float16 bytes
    return torch.from_numpy(np.array(initial_state, dtype=np.float32)).to(device)


def checked_arrays(batch: TraceArrays, network: NetworkConfig, learner: LearnerConfig
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
    """The batch's arrays, observations C-contiguous, once they fit the configured sizes (else a ValueError);
    the initial state only where learner.stored_state uses it."""
    trace_length = learner.trace_length
    observations = np.asarray(batch.observations)
    frame = (network.frame_height, network.frame_width, network.frame_channels)
    if observations.dtype != np.uint8 or observations.ndim != 5 or observations.shape[1:] != (trace_length + 1, *frame):
        raise ValueError(f"observations must be uint8 (B, {trace_length + 1}, {', '.join(map(str, frame))}), "
                         f"got {observations.dtype} {observations.shape}")
    steps = (observations.shape[0], trace_length)
    actions, rewards, terminated = (np.asarray(a) for a in (batch.actions, batch.rewards, batch.terminated))
    for name, array in (("actions", actions), ("rewards", rewards), ("terminated", terminated)):
        if array.shape != steps:
            raise ValueError(f"{name} must have shape {steps}, got {array.shape}")
    if not np.issubdtype(actions.dtype, np.integer) or actions.min() < 0 or actions.max() >= network.n_actions:
        raise ValueError(f"actions must be integers in [0, {network.n_actions}), got {actions.dtype} {actions.min()}..{actions.max()}")
    if not np.isfinite(rewards).all():
        raise ValueError("rewards must be finite")
    if not np.isin(terminated, (0, 1)).all():
        raise ValueError("terminated must hold only 0/1 or booleans")
    return np.ascontiguousarray(observations), actions, rewards, terminated, _checked_state(batch, network, learner)


def _checked_state(batch: TraceArrays, network: NetworkConfig, learner: LearnerConfig) -> np.ndarray | None:
    if not learner.stored_state:
        return None
    rows = None if batch.initial_state is None else np.asarray(batch.initial_state)
    expected = (len(batch.actions), 2, network.lstm_units)
    if rows is None or rows.shape != expected or not np.issubdtype(rows.dtype, np.floating):
        raise ValueError(f"initial_state must be floats {expected} (learner.stored_state), got "
                         f"{'none' if rows is None else f'{rows.dtype} {rows.shape}'}")
    if not np.isfinite(rows).all():
        raise ValueError("initial_state must be finite")
    return rows


class _PinnedSlot:
    """Page-locked host copies of one batch's arrays, and the event after which they may be rewritten."""

    def __init__(self, observations: tuple[int, ...], steps: tuple[int, int]) -> None:
        self.observations = torch.empty(observations, dtype=torch.uint8, pin_memory=True)
        self.actions = torch.empty(steps, dtype=torch.int64, pin_memory=True)
        self.rewards = torch.empty(steps, dtype=torch.float32, pin_memory=True)
        self.terminated = torch.empty(steps, dtype=torch.float32, pin_memory=True)
        self.copied: torch.cuda.Event | None = None

    def fits(self, observations: tuple[int, ...]) -> bool:
        return tuple(self.observations.shape) == observations


class BatchStager:
    """Gets batches onto the learner's device ahead of their update, from other threads (the prefetcher's).

    On CUDA: each batch is written into one of `slots` page-locked host buffers
    (reused in turn, after the copy that last read it has finished) and copied
    with non-blocking copies on a side stream; the update waits for the copy's
    event on its own stream, so the copy of batch k + 1 overlaps update k. On
    CPU the arrays are used in place (no copy) and, for the trace passes, the
    frames are scaled here, off the update's critical path.
    """

    def __init__(self, learner: "DoubleQLearner", slots: int = 2) -> None:
        self.learner = learner
        self.device = learner.device
        self._slots: list[_PinnedSlot] = []
        self._slot_count = slots
        self._next = 0
        self._stream = torch.cuda.Stream(self.device) if self.device.type == "cuda" else None
        self._lock = threading.Lock()  # the prefetcher's workers stage concurrently

    def stage(self, batch: TraceArrays) -> TraceTensors:
        learner = self.learner
        arrays = checked_arrays(batch, learner.network_config, learner.config)
        if self._stream is None:
            tensors = _on_device(arrays, self.device)
            if learner.stages_pixels:
                if threading.current_thread() is not threading.main_thread():
                    torch.set_num_threads(1)  # the update's threads own the cores; this thread fills their gaps
                pixels = scale_frames(tensors.observations, learner.online.used_frame_size)
                tensors = dataclasses.replace(tensors, pixels=pixels)
            return tensors
        with self._lock:
            slot = self._slot(arrays[0].shape, arrays[1].shape)
            if slot.copied is not None:
                slot.copied.synchronize()  # the copy that last read this slot is done
            for pinned, array in zip((slot.observations, slot.actions, slot.rewards, slot.terminated), arrays[:4]):
                pinned.numpy()[...] = array
            with torch.cuda.stream(self._stream):
                copies = [pinned.to(self.device, non_blocking=True)
                          for pinned in (slot.observations, slot.actions, slot.rewards, slot.terminated)]
                initial_state = _state_on(arrays[4], self.device)
                slot.copied = torch.cuda.Event()
                slot.copied.record(self._stream)
            return TraceTensors(*copies, initial_state=initial_state, ready=slot.copied)

    def _slot(self, observations: tuple[int, ...], steps: tuple[int, int]) -> _PinnedSlot:
        if len(self._slots) < self._slot_count:
            self._slots.append(_PinnedSlot(observations, steps))
            return self._slots[-1]
        slot = self._slots[self._next]
        self._next = (self._next + 1) % self._slot_count
        if not slot.fits(observations):
            if slot.copied is not None:
                slot.copied.synchronize()
            slot = self._slots[self._slots.index(slot)] = _PinnedSlot(observations, steps)
        return slot


def _wait_until_ready(tensors: TraceTensors) -> None:
    """Makes the current CUDA stream wait for a staged batch's copies and keeps their memory until it is done."""
    if tensors.ready is None:
        return
    stream = torch.cuda.current_stream(tensors.observations.device)
    stream.wait_event(tensors.ready)
    for tensor in (tensors.observations, tensors.actions, tensors.rewards, tensors.terminated):
        tensor.record_stream(stream)


