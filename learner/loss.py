"""The D3RQN's loss: Double-Q targets, the masked squared error, and the two implementations of the one
pass over a trace (learner/update.py's docstring states the method and the order of a step).

one_pass_loss runs D3RQN.forward under autograd; trace_pass_loss runs D3RQN.trace_q_values, the
hand-written passes (common/network.py); they agree within rounding.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import torch

from common.network import D3RQN, RecurrentState
from common.trace_pass import scale_frames
from common.stored_state import lstm_state
from learner.trace_batch import TraceTensors


@dataclass
class LossTerms:
    """What a loss function hands back to the update step."""

    loss: torch.Tensor  # scalar, with gradient
    q_values: torch.Tensor  # (B, T, A) online Q(h_t, .), detached
    next_q_values: torch.Tensor  # (B, T, A) online Q(h_t+1, .), detached


LossFunction = Callable[[D3RQN, D3RQN, TraceTensors, float, int, int], LossTerms]  # ..., gamma, n_mask, n_step


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

