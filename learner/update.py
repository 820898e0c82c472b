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

With learner.shift_pad (beyond the paper, DrQ's random shift) each trace's frames are first shifted by one
offset for all its steps (learner/frame_shift.py); every pass below reads the shifted frames.

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
(BatchStager, from the prefetcher's threads). The loss is learner/loss.py, the
batches learner/trace_batch.py, the timings that choose a path and a precision
learner/update_path.py; this module is the step itself (DoubleQLearner).
"""

from __future__ import annotations

import copy
import dataclasses
import logging
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
import torch

from common import cpu_capability
from common.config import LearnerConfig, NetworkConfig
from common.exploration.bmc import greedy_and_uniform_returns
from common.network import D3RQN, initial_network, resolve_device, weights_to_numpy
from learner.allocator import keep_freed_memory
from learner.frame_shift import draw_offsets, shift_frames
from learner.loss import (LossFunction, LossTerms, burn_in_steps, one_pass_terms, start_state, taken_action_values,
                          trace_pass_loss, trace_pixels)
from learner.trace_batch import BatchStager, TraceArrays, TraceTensors, _wait_until_ready, to_tensors
from learner.update_path import UPDATE_PATHS, choose_learner_precision, choose_update_path
from learner.step_size import clip_gradient, set_learning_rate
from learner.weight_average import WeightAverage

log = logging.getLogger("learner.update")


GRAD_NORM_EVERY = 10  # updates between measures of the gradient's norm (a read of 12 M gradients, ~1% of an update)


@dataclass
class UpdateResult:
    """The loss and what the exploration strategies need, over the unmasked steps t >= n_mask."""

    update: int  # how many updates have been made, this one included
    loss: float
    q_before: np.ndarray  # (B, T - n_mask) Q(h_t, a*_t) before the step, a* greedy before the step
    q_after: np.ndarray | None  # the same histories and actions after the step (only when asked)
    g_greedy: np.ndarray  # (B, T - n_mask) BMC's G_Q from the online Q(h_t+1, .)
    g_uniform: np.ndarray  # (B, T - n_mask) BMC's G_U
    grad_norm: float | None = None  # the gradient's global norm before any clip, every GRAD_NORM_EVERY updates



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
        # beyond the paper: a slow average of the online weights, for kept policies only (learner/weight_average.py)
        self.average = WeightAverage(self.online, learner.ema_updates) if learner.ema_updates > 0 else None
        # beyond the paper: DrQ's random shifts (learner/frame_shift.py), from a generator of their own, so that the
        # shifts follow from learner.seed and nothing else draws from it
        self.shifts = torch.Generator().manual_seed(learner.seed) if learner.shift_pad > 0 else None
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

    @property
    def stages_pixels(self) -> bool:
        """Whether staged batches carry their frames scaled ahead (the trace passes read them so); not when
        they are shifted first, at the update."""
        return self.loss_function is trace_pass_loss and self.shifts is None

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
        tensors = self.shifted(tensors)
        if self.precision == "auto":
            self.use_precision(choose_learner_precision(self, tensors))
        if self.update_path == "auto":
            self.use_path(choose_update_path(self, tensors))
        return self._update(tensors, with_q_after)

    def shifted(self, tensors: TraceTensors) -> TraceTensors:
        """The batch with each trace's frames shifted by one offset (learner.shift_pad), or as it is when off.

        Drawn here, in the order of the updates rather than of the prefetcher's threads, so that a run is the same
        from the same seed; every pass of the update (online, target, VDBE's after) reads these frames."""
        if self.shifts is None:
            return tensors
        offsets = draw_offsets(self.shifts, tensors.observations.shape[0], self.config.shift_pad)
        return dataclasses.replace(tensors, observations=shift_frames(tensors.observations, offsets), pixels=None)

    def _update(self, tensors: TraceTensors, with_q_after: bool) -> UpdateResult:
        if self.split_passes:
            terms = self._split_trace_pass_loss(tensors)
        else:
            self.soft_update_target()
            terms = self.loss_function(self.online, self.target, tensors, self.config.gamma,
                                       self.config.masked_steps, self.config.n_step)
        self.optimizer.zero_grad(set_to_none=True)
        terms.loss.backward()
        grad_norm = clip_gradient(self.online.parameters(), self.config,
                                  measure=self.updates % GRAD_NORM_EVERY == 0)
        set_learning_rate(self.optimizer, self.config, self.updates)
        self.optimizer.step()
        self.updates += 1
        if self.average is not None:
            self.average.update(self.online, self.updates)
        return dataclasses.replace(self.exploration_terms(tensors, terms, with_q_after), grad_norm=grad_norm)

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
        average = {"ema": self.average.state_dict()} if self.average is not None else {}
        shifts = {"shifts": self.shifts.get_state()} if self.shifts is not None else {}
        return {
            "online": self.online.state_dict(),
            "target": self.target.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "updates": self.updates,
            **average,
            **shifts,
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
        if self.average is not None:
            self._load_average(state.get("ema"))
        if self.shifts is not None and "shifts" in state:  # a checkpoint from before the shifts: drawn from the seed
            self.shifts.set_state(state["shifts"])

    def _load_average(self, state: dict | None) -> None:
        if state is None:
            log.warning("learner.ema_updates is on but the checkpoint holds no moving average: it starts again "
                        "from the weights of update %d", self.updates)
            self.average.restart(self.online)
            return
        self.average.load_state_dict(state)

    def scratch_copy(self) -> "DoubleQLearner":
        """A deep copy to time updates on, its LSTMs packed as the original's."""
        scratch = copy.deepcopy(self)
        _packed(scratch.online), _packed(scratch.target)
        return scratch


# name: (loss function, soft update and target pass on a helper thread)

_helper: ThreadPoolExecutor | None = None


def _helper_thread() -> ThreadPoolExecutor:
    global _helper
    if _helper is None:
        _helper = ThreadPoolExecutor(max_workers=1, thread_name_prefix="learner-target-pass")
    return _helper



def _packed(network: D3RQN) -> D3RQN:
    # deepcopy splits cuDNN's single LSTM weight buffer; unpacked, every CUDA call re-packs it (a no-op on CPU)
    network.lstm.flatten_parameters()
    return network



def _adam(parameters, lr: float) -> torch.optim.Adam:
    """Adam, fused into one kernel where this torch supports it (on CPU from 2.4): ~10x faster here."""
    parameters = list(parameters)
    try:
        return torch.optim.Adam(parameters, lr=lr, fused=True)
    except RuntimeError:
        return torch.optim.Adam(parameters, lr=lr)


def _numpy(tensor: torch.Tensor) -> np.ndarray:
    return tensor.detach().cpu().numpy()
