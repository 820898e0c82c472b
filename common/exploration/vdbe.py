"""Value-difference based exploration (VDBE), and VDBE-Softmax, whose exploring actions are softmax samples.

``on_update(q_before, q_after)``: Q(h, a*) of the same histories and greedy actions a* (greedy under
the weights before the update), under the weights before and after one gradient step. A batch gives
one Delta per history; the paper's rule updates epsilon once per network update, so this does it once
per call with f averaged over the batch: eps <- lambda * mean_i f(Delta_i) + (1 - lambda) * eps.
Averaging f (not Delta) keeps each history's contribution bounded by 1, as in the tabular rule.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from common.exploration.base import ExplorationStrategy
from common.exploration.boltzmann import SoftmaxConfig
from common.schema.fields import check_positive, check_probability, option


@dataclass
class VdbeConfig:
    """VDBE: epsilon follows how much each update changes Q (also VDBE-Softmax's epsilon)."""

    lam: float = option(0.2, "lambda, the weight of each update's f(Delta) in epsilon (1 / number of actions), "
                             "in [0, 1]")
    nu: float = option(1.0, "inverse sensitivity: f = (1 - e^(-|Delta|/nu)) / (1 + e^(-|Delta|/nu))")
    eps0: float = option(1.0, "epsilon when updates start, in [0, 1]")

    def validate(self) -> None:
        check_probability(self, "lam", "eps0")
        check_positive(self, "nu")


def vdbe_f(delta: np.ndarray | float, nu: float) -> np.ndarray:
    """f = (1 - e^(-|Delta|/nu)) / (1 + e^(-|Delta|/nu)), in [0, 1)."""
    decay = np.exp(-np.abs(delta) / nu)
    return (1.0 - decay) / (1.0 + decay)


@dataclass(frozen=True)
class VdbeState:
    """VDBE's own state: the epsilon its updates have moved so far."""

    epsilon: float

    def validate(self) -> None:
        check_probability(self, "epsilon")


class Vdbe(ExplorationStrategy):
    """Value-difference based exploration: epsilon follows how much an update moves Q(h, a*)."""

    name = "vdbe"
    needs_q_after = True
    state_type = VdbeState

    def __init__(self, n_actions: int, config: VdbeConfig) -> None:
        super().__init__(n_actions, config)
        self._eps = config.eps0

    def on_update(self, q_before: np.ndarray, q_after: np.ndarray) -> None:
        before = np.asarray(q_before, dtype=np.float64)
        after = np.asarray(q_after, dtype=np.float64)
        if before.shape != after.shape or before.size == 0 or not np.isfinite(after - before).all():
            raise ValueError(f"q_before {before.shape} and q_after {after.shape} must be equal-shaped, "
                             "non-empty and finite")
        super().on_update(before, after)
        mean_f = float(np.mean(vdbe_f(after - before, self.config.nu)))
        self._eps = self.config.lam * mean_f + (1.0 - self.config.lam) * self._eps

    def _epsilon(self) -> float:
        return self._eps

    def own_state(self) -> VdbeState:
        return VdbeState(self._eps)

    def _restore(self, state: VdbeState) -> None:
        self._eps = state.epsilon


class VdbeSoftmax(Vdbe):
    """Max-Boltzmann exploration whose epsilon follows the VDBE rule."""

    name = "vdbe_softmax"

    def __init__(self, n_actions: int, config: VdbeConfig, softmax: SoftmaxConfig) -> None:
        super().__init__(n_actions, config)
        self.softmax = softmax

    def sections(self) -> tuple:
        return (self.config, self.softmax)

    def _kappa(self) -> float:
        return self.softmax.kappa
