"""Beyond the paper: the step of the update late in a run (learner.lr_decay_from, lr_decay_to, lr_final_scale) and
a bound on the gradient's norm (learner.grad_clip_norm), two remedies for a greedy policy that swings between
checkpoints.

A smaller step late in training lets the weights settle where a constant one keeps them moving (the
policy-churn account of Schaul et al. 2022: the greedy action changes in many states within a few updates,
more so with larger steps); the rate falls linearly from learner.lr at lr_decay_from updates to lr x
lr_final_scale at lr_decay_to and stays there. Clipping the gradient's global norm (Ape-X and R2D2 clip it at
40; Kapturowski et al. 2019) bounds the largest steps, those that a rare large error makes. Both are off by
default: the paper's Adam step is unchanged then, bit for bit.
"""

from __future__ import annotations

import torch

from common.config import LearnerConfig


def learning_rate(config: LearnerConfig, updates: int) -> float:
    """The rate of the update that follows `updates` updates."""
    lr, start, end = config.lr, config.lr_decay_from, config.lr_decay_to
    if start <= 0 or updates <= start:
        return lr
    share = min(1.0, (updates - start) / (end - start))
    return lr * (1.0 - share * (1.0 - config.lr_final_scale))


def set_learning_rate(optimizer: torch.optim.Optimizer, config: LearnerConfig, updates: int) -> None:
    """Sets the rate of the coming update, where a decay is on (else the optimiser is left as built)."""
    if config.lr_decay_from > 0:
        for group in optimizer.param_groups:
            group["lr"] = learning_rate(config, updates)


def clip_gradient(parameters, config: LearnerConfig, measure: bool = False) -> float | None:
    """Scales the gradients to a global norm of at most learner.grad_clip_norm, where on; returns their norm
    before any clip where clipping or `measure` (the learner's figures, which a clip threshold is chosen from),
    else None. Measuring only reads the gradients."""
    parameters = list(parameters)
    if config.grad_clip_norm > 0:
        return float(torch.nn.utils.clip_grad_norm_(parameters, config.grad_clip_norm, foreach=True))
    if not measure:
        return None
    grads = [parameter.grad for parameter in parameters if parameter.grad is not None]
    return float(torch.nn.utils.get_total_norm(grads, foreach=True)) if grads else 0.0
