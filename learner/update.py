"""One learner step of the D3RQN: Double-Q targets, masked squared error, Adam, soft target update.

A batch holds B traces of T steps: observations s_0..s_T (T + 1 frames), the
actions a_t taken in s_t, the rewards r_t and the flags ``terminated[t]``
("s_t+1 ends the episode"). Every trace starts from a zero LSTM state (the
paper's), or, with learner.stored_state (beyond the paper, R2D2's), from the
state the actor held before s_0: then the first learner.burn_in steps run
without gradient and are the masked ones (n_mask stands for burn_in below).

Per step (docs/method.md, "The update"), in this order:

1. soft target update, *before* the gradient step as the authors' code does:
   target <- tau * online + (1 - tau) * target; so the targets of step k
   already use the target net updated k times;
2. y_t = r_t + gamma * (1 - terminated_t) * Q_target(h_t+1, argmax_a Q_online(h_t+1, a));
   a truncated episode (the 2,000-step cut) is not terminated, so it bootstraps
   (learner.n_step, beyond the paper, sums n rewards before the bootstrap: double_q_targets);
3. loss = sum over b, t >= n_mask of (y_t - Q_online(h_t, a_t))^2 / (B * T): the
   paper's Algorithm 1, L_j = sum_i w_i (Y_ji - Q_ji)^2 / T with w_i = 0 for the
   first n_mask steps, averaged over the B traces;
4. one Adam step.

Afterwards, for the exploration strategies (unmasked steps only): Q(h_t, a*_t)
before the step (a* greedy before the step, from the same pass), optionally
the same after the step (one more no-grad pass, only for VDBE), and BMC's G_Q,
G_U from the online next-state Q-values with (1 - terminated) applied.

"Do the work once": the online network runs once over all T + 1 frames and
gives both Q(h_t, .) for t < T (with gradient) and Q(h_t+1, .) for the argmax
(detached); the target network runs once over the same frames without
gradient. In the paper's algorithm the next-state passes start from a zero
state at s_1, so h_t+1 there has seen s_1..s_t+1; here it has seen s_0..s_t+1,
one frame more, the same history the online Q(h_t, .) is built on. The
separate-pass versions, with either history, live in deploy/bench/reference_update.py.

Two implementations of that one pass give the same loss and gradients within
rounding: one_pass_loss runs D3RQN.forward under autograd (nn.LSTM; cuDNN on
CUDA); trace_pass_loss runs D3RQN.trace_q_values, hand-written passes that do
less work on the CPU (common/network.py says what they skip). The learner picks
one per `learner.update_path`, by default by timing both on its first batch.
Batches can be checked, decoded and put on the device ahead of their update
(BatchStager, from the prefetcher's threads).
"""

from __future__ import annotations

import copy
import dataclasses
import logging
import math
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch

from common import cpu_capability
from common.config import LearnerConfig, NetworkConfig
from common.exploration.bmc import greedy_and_uniform_returns
from common.network import (D3RQN, RecurrentState, initial_network, resolve_device, scale_frames,
                            weights_to_numpy)
from common.stored_state import lstm_state
from learner.allocator import keep_freed_memory

log = logging.getLogger("learner.update")


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


@dataclass
class LossTerms:
    """What a loss function hands back to the update step."""

    loss: torch.Tensor  # scalar, with gradient
    q_values: torch.Tensor  # (B, T, A) online Q(h_t, .), detached
    next_q_values: torch.Tensor  # (B, T, A) online Q(h_t+1, .), detached


LossFunction = Callable[[D3RQN, D3RQN, TraceTensors, float, int, int], LossTerms]  # ..., gamma, n_mask, n_step


@dataclass
class UpdateResult:
    """The loss and what the exploration strategies need, over the unmasked steps t >= n_mask."""

    update: int  # how many updates have been made, this one included
    loss: float
    q_before: np.ndarray  # (B, T - n_mask) Q(h_t, a*_t) before the step, a* greedy before the step
    q_after: np.ndarray | None  # the same histories and actions after the step (only when asked)
    g_greedy: np.ndarray  # (B, T - n_mask) BMC's G_Q from the online Q(h_t+1, .)
    g_uniform: np.ndarray  # (B, T - n_mask) BMC's G_U


def double_q_targets(rewards: torch.Tensor, terminated: torch.Tensor, next_q_online: torch.Tensor,
                     next_q_target: torch.Tensor, gamma: float, n_step: int = 1) -> torch.Tensor:
    """y_t = sum_{k<m} gamma^k r_t+k + gamma^m Q_target(h_t+m, argmax_a Q_online(h_t+m, a)), m = min(n_step, T - t).

    The paper's target is n_step 1: y = r + gamma * (1 - terminal) * Q_target(h', argmax_a Q_online(h', a)).
    With more steps (learner.n_step, beyond the paper) a terminal inside the window stops both the sum and
    the bootstrap, and the trace's end shortens the window (its last steps bootstrap from s_T); a truncated
    episode (the 2,000-step cut) is not terminal, so it bootstraps."""
    greedy = next_q_online.argmax(dim=-1, keepdim=True)
    bootstrap = next_q_target.gather(-1, greedy).squeeze(-1)  # (B, T): the value of s_t+1
    if n_step == 1:
        return rewards + gamma * (1.0 - terminated) * bootstrap
    steps, columns = rewards.shape[-1], []
    for t in range(steps):
        total, alive, discount = torch.zeros_like(rewards[..., t]), torch.ones_like(rewards[..., t]), 1.0
        last = min(t + n_step, steps) - 1  # the window's last step: its next state is bootstrapped
        for k in range(t, last + 1):
            total = total + discount * alive * rewards[..., k]
            alive = alive * (1.0 - terminated[..., k])
            discount *= gamma
        columns.append(total + discount * alive * bootstrap[..., last])
    return torch.stack(columns, dim=-1)


def masked_squared_error(q_taken: torch.Tensor, targets: torch.Tensor, n_mask: int) -> torch.Tensor:
    """Mean over all B * T errors with the first n_mask of each trace weighted 0."""
    weights = torch.ones_like(q_taken)
    weights[:, :n_mask] = 0.0
    return (weights * (targets - q_taken) ** 2).mean()


def taken_action_values(q_values: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
    return q_values.gather(-1, actions.unsqueeze(-1)).squeeze(-1)


def start_state(batch: TraceTensors) -> RecurrentState | None:
    """The LSTM state the batch's traces start from: the stored one, or None for the zero state."""
    return None if batch.initial_state is None else lstm_state(batch.initial_state)


def burn_in_steps(batch: TraceTensors, n_mask: int) -> int:
    """Leading steps that run without gradient: the masked ones of traces from a stored state (R2D2's
    burn-in); none from the zero state, whose masked steps pass the later errors' gradient on (the paper's)."""
    return 0 if batch.initial_state is None else n_mask


def burnt_in_forward(online: D3RQN, observations: torch.Tensor, state: RecurrentState | None,
                     burn_in: int) -> torch.Tensor:
    """Q(h_t, .) from D3RQN.forward with the first burn_in steps run without gradient."""
    if not burn_in:
        return online(observations, state)[0]
    with torch.no_grad():
        burnt, state = online(observations[:, :burn_in], state)
    return torch.cat([burnt, online(observations[:, burn_in:], state)[0]], dim=1)


def one_pass_loss(online: D3RQN, target: D3RQN, batch: TraceTensors, gamma: float, n_mask: int,
                  n_step: int = 1) -> LossTerms:
    """One online pass (with gradient past any burn-in) and one target pass (without) over s_0..s_T.

    s_T goes through the gradient pass too although no loss term differentiates
    Q(h_T): running it in a separate no-grad call instead costs more (~10 ms,
    mostly reading the 44 MB LSTM input weights once more) than the backward
    pass spends on it (~6 ms), measured at the paper's sizes on the 2-core CPU.
    """
    state = start_state(batch)
    q_all = burnt_in_forward(online, batch.observations, state, burn_in_steps(batch, n_mask))
    with torch.no_grad():
        next_q_target = target(batch.observations, state)[0][:, 1:]
    return one_pass_terms(q_all, next_q_target, batch, gamma, n_mask, n_step)


def one_pass_terms(q_all: torch.Tensor, next_q_target: torch.Tensor, batch: TraceTensors, gamma: float,
                   n_mask: int, n_step: int = 1) -> LossTerms:
    """The loss from the online Q(h_0..h_T, .) (with gradient) and the target Q(h_1..h_T, .)."""
    q_values, next_q_online = q_all[:, :-1], q_all[:, 1:].detach()
    targets = double_q_targets(batch.rewards, batch.terminated, next_q_online, next_q_target, gamma, n_step)
    loss = masked_squared_error(taken_action_values(q_values, batch.actions), targets, n_mask)
    return LossTerms(loss, q_values.detach(), next_q_online)


def trace_pass_loss(online: D3RQN, target: D3RQN, batch: TraceTensors, gamma: float, n_mask: int,
                    n_step: int = 1) -> LossTerms:
    """one_pass_loss on D3RQN.trace_q_values: the same loss and gradients (within rounding), less work on the CPU.

    The frames are scaled once for both networks, and s_T, whose online Q-values
    only enter the loss detached (the argmax), is left out of the backward pass.
    """
    traces, trace_length = batch.actions.shape
    pixels, state = trace_pixels(batch, online), start_state(batch)
    q_all = online.trace_q_values(pixels, traces, grad_steps=trace_length, state=state,
                                  burn_in=burn_in_steps(batch, n_mask))
    with torch.no_grad():
        next_q_target = target.trace_q_values(pixels, traces, state=state)[:, 1:]
    return one_pass_terms(q_all, next_q_target, batch, gamma, n_mask, n_step)


def trace_pixels(batch: TraceTensors, network: D3RQN) -> torch.Tensor:
    """The batch's frames as the trace passes read them: staged ahead, or scaled now."""
    if batch.pixels is not None:
        return batch.pixels
    return scale_frames(batch.observations, network.used_frame_size)


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
            if learner.loss_function is trace_pass_loss:
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


class DoubleQLearner:
    """The online and target networks, the optimiser, and the update step.

    Constructing one sets the process's allocator to keep freed memory
    (learner/allocator.py): 10-18% more updates per second on CPU.

    Without a loss_function, `learner.update_path` picks how the passes are
    computed (UPDATE_PATHS), all with the same loss and gradients within
    rounding: "trace" (trace_pass_loss), "trace-split" (the same, with the soft
    update and the target pass on a helper thread with half the torch threads
    while the online forward pass runs on the other half), "autograd"
    (one_pass_loss); "auto" times them on the first batch and keeps the fastest
    for every learner of the process with the same device, sizes and thread
    count (choose_update_path).
    """

    def __init__(self, network: NetworkConfig, learner: LearnerConfig, loss_function: LossFunction | None = None,
                 device: torch.device | None = None) -> None:
        self.network_config = network
        self.config = learner
        self.device = device if device is not None else resolve_device(network)
        keep_freed_memory()
        self.online = initial_network(network, learner.seed).to(self.device)
        self.target = _packed(copy.deepcopy(self.online)).requires_grad_(False)
        self.optimizer = _adam(self.online.parameters(), learner.lr)
        self.updates = 0
        self.split_passes = False  # the target pass on a helper thread (update path "trace-split")
        self.precision = learner.precision  # "auto" until the first batch has timed both
        if self.precision != "auto":
            self.use_precision(self.precision)
        if loss_function is not None:
            self.loss_function: LossFunction | None = loss_function
            self.update_path = next((name for name, (function, split) in UPDATE_PATHS.items()
                                     if function is loss_function and not split), "custom")
        else:
            self.use_path(learner.update_path)
        if self.precision == "bfloat16" and self.update_path in ("autograd", "custom"):
            # what is reported must be what is computed: forward() and custom losses compute float32 throughout
            raise ValueError(f"learner.precision bfloat16 runs on the trace paths only, not on update path "
                             f"{self.update_path}")

    def use_precision(self, precision: str) -> None:
        """The trace passes' convolutions and input projection in float32 or bfloat16 (learner.precision).

        An explicit bfloat16 that this CPU cannot run raises cpu_capability.PrecisionUnavailable."""
        if self.device.type == "cpu":
            cpu_capability.require_precision("learner.precision", precision)
        self.online.trace_dtype = self.target.trace_dtype = getattr(torch, precision)
        self.precision = precision

    def use_path(self, name: str) -> None:
        """Switches to one of UPDATE_PATHS, or to "auto" (chosen on the next batch)."""
        if name == "auto":
            self.loss_function, self.split_passes = None, False
        else:
            self.loss_function, self.split_passes = UPDATE_PATHS[name]
        self.update_path = name

    def prepare(self, batch: TraceArrays) -> TraceTensors:
        """Checks a batch and moves it to the learner's device (the copy-in part of update())."""
        return to_tensors(batch, self.network_config, self.config, self.device)

    def stager(self) -> BatchStager:
        """A BatchStager for this learner: stage(batch) in the prefetch thread, update(staged) in the loop."""
        return BatchStager(self)

    def update(self, batch: TraceArrays | TraceTensors, with_q_after: bool = False) -> UpdateResult:
        """One soft target update and one gradient step; with_q_after adds VDBE's extra forward pass.

        `batch` may come prepared (prepare(), or a BatchStager ahead of time).
        """
        tensors = batch if isinstance(batch, TraceTensors) else self.prepare(batch)
        _wait_until_ready(tensors)
        if self.precision == "auto":
            self.use_precision(choose_learner_precision(self, tensors))
        if self.update_path == "auto":
            self.use_path(choose_update_path(self, tensors))
        return self._update(tensors, with_q_after)

    def _update(self, tensors: TraceTensors, with_q_after: bool) -> UpdateResult:
        if self.split_passes:
            terms = self._split_trace_pass_loss(tensors)
        else:
            self.soft_update_target()
            terms = self.loss_function(self.online, self.target, tensors, self.config.gamma,
                                       self.config.masked_steps, self.config.n_step)
        self.optimizer.zero_grad(set_to_none=True)
        terms.loss.backward()
        self.optimizer.step()
        self.updates += 1
        return self.exploration_terms(tensors, terms, with_q_after)

    def _split_trace_pass_loss(self, batch: TraceTensors) -> LossTerms:
        """trace_pass_loss with the soft target update and the target pass on a helper thread.

        The two threads share torch's threads: no OpenMP team spans both passes,
        which keeps them apart on a machine whose cores are busy with other work.
        """
        traces, trace_length = batch.actions.shape
        pixels, state = trace_pixels(batch, self.online), start_state(batch)
        burn_in = burn_in_steps(batch, self.config.masked_steps)
        threads = torch.get_num_threads()
        helper_threads = max(1, threads // 2)

        def soft_update_and_target_pass() -> torch.Tensor:
            torch.set_num_threads(helper_threads)
            self.soft_update_target()
            with torch.no_grad():
                return self.target.trace_q_values(pixels, traces, state=state)[:, 1:]

        pending = _helper_thread().submit(soft_update_and_target_pass)
        torch.set_num_threads(max(1, threads - helper_threads))
        try:
            q_all = self.online.trace_q_values(pixels, traces, grad_steps=trace_length, state=state, burn_in=burn_in)
        finally:
            torch.set_num_threads(threads)
            next_q_target = pending.result()
        return one_pass_terms(q_all, next_q_target, batch, self.config.gamma, self.config.masked_steps,
                              self.config.n_step)

    def exploration_terms(self, tensors: TraceTensors, terms: LossTerms, with_q_after: bool) -> UpdateResult:
        """What the strategies need from an update whose gradient step is done (the last part of update())."""
        n_mask = self.config.masked_steps
        q_unmasked = terms.q_values[:, n_mask:]
        greedy = q_unmasked.argmax(dim=-1)
        q_after = self._greedy_q_after(tensors, greedy) if with_q_after else None
        g_greedy, g_uniform = greedy_and_uniform_returns(
            _numpy(tensors.rewards[:, n_mask:]), _numpy(terms.next_q_values[:, n_mask:]),
            _numpy(tensors.terminated[:, n_mask:]), self.config.gamma)
        return UpdateResult(
            update=self.updates,
            loss=float(terms.loss.detach()),
            q_before=_numpy(taken_action_values(q_unmasked, greedy)),
            q_after=q_after,
            g_greedy=g_greedy,
            g_uniform=g_uniform,
        )

    @torch.no_grad()
    def soft_update_target(self) -> None:
        """target <- tau * online + (1 - tau) * target, one fused op over all parameters."""
        target = list(self.target.parameters())
        online = [p.detach() for p in self.online.parameters()]
        torch._foreach_lerp_(target, online, self.config.tau)

    @torch.no_grad()
    def _greedy_q_after(self, tensors: TraceTensors, greedy: torch.Tensor) -> np.ndarray:
        """Q(h_t, a*_t) under the updated weights, for the unmasked steps (over s_0..s_T-1)."""
        traces, trace_length = tensors.actions.shape
        state = start_state(tensors)
        if self.loss_function is trace_pass_loss:
            pixels = trace_pixels(tensors, self.online)[:trace_length * traces]  # time-major: s_T is the last rows
            q_values = self.online.trace_q_values(pixels, traces, state=state)
        else:
            q_values, _ = self.online(tensors.observations[:, :-1], state)
        return _numpy(taken_action_values(q_values[:, self.config.masked_steps:], greedy))

    def online_weights(self) -> dict[str, np.ndarray]:
        """The online network as numpy arrays, for the Weights message."""
        return weights_to_numpy(self.online)

    def state_dict(self) -> dict:
        return {
            "online": self.online.state_dict(),
            "target": self.target.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "updates": self.updates,
        }

    def load_state_dict(self, state: dict) -> None:
        missing = {"online", "target", "optimizer", "updates"} - set(state)
        if missing:
            raise ValueError(f"learner checkpoint lacks {sorted(missing)}")
        try:
            self.online.load_state_dict(state["online"])
            self.target.load_state_dict(state["target"])
            self.optimizer.load_state_dict(state["optimizer"])
        except (RuntimeError, KeyError) as error:
            raise ValueError(f"learner checkpoint does not fit this network: {error}") from None
        self.updates = int(state["updates"])

    def scratch_copy(self) -> "DoubleQLearner":
        """A deep copy to time updates on, its LSTMs packed as the original's."""
        scratch = copy.deepcopy(self)
        _packed(scratch.online), _packed(scratch.target)
        return scratch


# name: (loss function, soft update and target pass on a helper thread)
UPDATE_PATHS: dict[str, tuple[LossFunction, bool]] = {
    "trace": (trace_pass_loss, False),
    "trace-split": (trace_pass_loss, True),
    "autograd": (one_pass_loss, False),
}

_chosen_paths: dict[tuple, str] = {}  # choose_update_path's measurements, per process
AUTO_BFLOAT16_SPEEDUP = 1.3  # learner.precision auto: a smaller gain is not worth other numbers than the paper's
_helper: ThreadPoolExecutor | None = None


def _helper_thread() -> ThreadPoolExecutor:
    global _helper
    if _helper is None:
        _helper = ThreadPoolExecutor(max_workers=1, thread_name_prefix="learner-target-pass")
    return _helper


def candidate_paths(device: torch.device, threads: int, precision: str = "float32") -> list[str]:
    """The update paths worth timing: "trace-split" needs two torch threads; on CUDA one stream does it all;
    bfloat16 runs on the trace paths only."""
    return [name for name in UPDATE_PATHS if (name != "trace-split" or (device.type == "cpu" and threads >= 2))
            and (name != "autograd" or precision == "float32")]


def choose_learner_precision(learner: DoubleQLearner, batch: TraceTensors, rounds: int = 5) -> str:
    """learner.precision auto: bfloat16 where the CPU does it natively and whole updates of the trace path
    time at least AUTO_BFLOAT16_SPEEDUP faster than in float32; float32 otherwise. One log line says why.

    The timings are made to hold when another process shares the CPU (issue 39: a busy neighbour once made
    bfloat16's 1.5x look like 1.1x): interleaved_cpu_seconds counts the CPU time of one torch thread, which a
    neighbour's time slices do not inflate, over several interleaved rounds, and the best of each is compared."""
    if learner.update_path in ("autograd", "custom"):
        log.info("learner.precision auto: float32, since learner.update_path %s computes in float32",
                 learner.update_path)
        return "float32"
    if learner.device.type != "cpu" or not cpu_capability.bfloat16_native():
        why = ("the learner is on " + learner.device.type if learner.device.type != "cpu" else
               cpu_capability.bfloat16_problem() or "this CPU has no native bfloat16 (AMX or AVX512-BF16)")
        log.info("learner.precision auto: float32, since %s", why)
        return "float32"
    scratch = learner.scratch_copy()
    scratch.use_path("trace")

    def update_in(precision: str) -> Callable[[], None]:
        def run() -> None:
            scratch.use_precision(precision)
            scratch._update(batch, with_q_after=False)
        return run

    seconds = interleaved_cpu_seconds({precision: update_in(precision) for precision in ("float32", "bfloat16")},
                                      rounds)
    del scratch
    chosen = precision_from_timings(seconds)
    best = {precision: min(times) for precision, times in seconds.items()}
    log.info("learner.precision auto: %s (best of %d interleaved updates each, CPU time on one thread: float32 "
             "%.1f ms, bfloat16 %.1f ms; bfloat16 is taken at %.1fx or more)", chosen, rounds,
             1e3 * best["float32"], 1e3 * best["bfloat16"], AUTO_BFLOAT16_SPEEDUP)
    return chosen


def precision_from_timings(seconds: dict[str, list[float]], speedup: float | None = None) -> str:
    """bfloat16 when its best time is at least `speedup` (AUTO_BFLOAT16_SPEEDUP) times shorter than float32's.

    The best (minimum) of the repeats: noise from other processes only ever adds time, so the minimum is the
    closest to what a quiet machine measures, where a mean or a single timing carries the neighbour's share."""
    speedup = AUTO_BFLOAT16_SPEEDUP if speedup is None else speedup
    return "bfloat16" if min(seconds["float32"]) >= speedup * min(seconds["bfloat16"]) else "float32"


def interleaved_cpu_seconds(candidates: dict[str, Callable[[], None]], rounds: int) -> dict[str, list[float]]:
    """The CPU seconds of each candidate in each of `rounds` rounds, after one untimed round (warm-up).

    Each round runs every candidate once, in turn, the order reversed every other round, so that a slow spell
    hits all alike. On one torch thread, timed by this thread's CPU clock: what the work costs, not how long
    a neighbour holds the core meanwhile (wall time under time-slicing; with two threads, the OpenMP team also
    waits for its slowest member). bfloat16 against float32 is a property of the arithmetic per core, so the
    one-thread ratio is the one that decides."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    names = list(candidates)
    seconds: dict[str, list[float]] = {name: [] for name in names}
    try:
        for round_ in range(rounds + 1):
            for name in (names if round_ % 2 == 0 else names[::-1]):
                started = time.thread_time()
                candidates[name]()
                if round_:
                    seconds[name].append(time.thread_time() - started)
    finally:
        torch.set_num_threads(threads)
    return seconds


def choose_update_path(learner: DoubleQLearner, batch: TraceTensors, rounds: int = 2) -> str:
    """The fastest update path for this learner's device, sizes and threads, measured once per process.

    Whole updates (soft update, passes, backward, Adam) on a scratch copy of the
    learner, so the learner itself is left as it was; each round times one update
    of each path in turn, after one untimed update each; the shortest best round wins.
    """
    threads = torch.get_num_threads()
    key = (learner.device.type, learner.device.index, dataclasses.astuple(learner.network_config),
           tuple(batch.observations.shape), threads, learner.precision)
    if key in _chosen_paths:
        return _chosen_paths[key]
    scratch = learner.scratch_copy()
    best = {name: math.inf for name in candidate_paths(learner.device, threads, learner.precision)}
    for round_ in range(rounds + 1):
        for name in best:
            scratch.use_path(name)
            _synchronize(learner.device)
            started = time.perf_counter()
            scratch._update(batch, with_q_after=False)
            _synchronize(learner.device)
            if round_:
                best[name] = min(best[name], time.perf_counter() - started)
    del scratch
    chosen = min(best, key=best.get)
    log.info("update path: %s (best of %d updates each with %d torch threads: %s)", chosen, rounds, threads,
             ", ".join(f"{name} {1e3 * seconds:.1f} ms" for name, seconds in best.items()))
    _chosen_paths[key] = chosen
    return chosen


def _packed(network: D3RQN) -> D3RQN:
    # deepcopy splits cuDNN's single LSTM weight buffer; unpacked, every CUDA call re-packs it (a no-op on CPU)
    network.lstm.flatten_parameters()
    return network


def _synchronize(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _adam(parameters, lr: float) -> torch.optim.Adam:
    """Adam, fused into one kernel where this torch supports it (on CPU from 2.4): ~10x faster here."""
    parameters = list(parameters)
    try:
        return torch.optim.Adam(parameters, lr=lr, fused=True)
    except RuntimeError:
        return torch.optim.Adam(parameters, lr=lr)


def _numpy(tensor: torch.Tensor) -> np.ndarray:
    return tensor.detach().cpu().numpy()
