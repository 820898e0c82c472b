"""The straightforward separate-pass loss, as the paper's algorithm lists it: the reference
that tests and the learner-speed benchmark compare the one-pass loss of learner/update.py with.

Three passes: online over s_0..s_T-1 for Q(h_t, .) (with gradient), online
again for the argmax over next-state Q, target for the next-state Q (both
without gradient).

``paper_history=True`` is the paper: the next-state passes run over s_1..s_T
from a zero state, so h_t+1 has seen s_1..s_t+1. ``paper_history=False`` runs
them over s_0..s_T and drops the first output, so h_t+1 has seen s_0..s_t+1,
which is what the one-pass loss computes; that variant must give the same loss.
"""

from __future__ import annotations

import functools

import torch

from common.network import D3RQN
from learner.loss import LossTerms, double_q_targets, masked_squared_error, taken_action_values
from learner.trace_batch import TraceTensors


def separate_pass_loss(online: D3RQN, target: D3RQN, batch: TraceTensors, gamma: float, n_mask: int,
                       n_step: int = 1, *, paper_history: bool = True) -> LossTerms:
    trace_length = batch.actions.shape[1]
    q_values, _ = online(batch.observations[:, :trace_length])
    with torch.no_grad():
        if paper_history:
            next_frames, skip = batch.observations[:, 1:], 0
        else:
            next_frames, skip = batch.observations, 1
        next_q_online = online(next_frames)[0][:, skip:]
        next_q_target = target(next_frames)[0][:, skip:]
    targets = double_q_targets(batch.rewards, batch.terminated, next_q_online, next_q_target, gamma, n_step)
    loss = masked_squared_error(taken_action_values(q_values, batch.actions), targets, n_mask)
    return LossTerms(loss, q_values.detach(), next_q_online)


paper_reference_loss = functools.partial(separate_pass_loss, paper_history=True)
same_history_reference_loss = functools.partial(separate_pass_loss, paper_history=False)
