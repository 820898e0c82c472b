"""The Boltzmann strategies, their parameters then their rules: Softmax (every action a softmax(Q / kappa)
sample) and Max-Boltzmann (greedy, or with probability epsilon a softmax sample)."""

from __future__ import annotations

from dataclasses import dataclass

from common.exploration.base import ExplorationStrategy
from common.schema.fields import check_positive, check_probability, option


@dataclass
class SoftmaxConfig:
    """Softmax (Boltzmann) exploration: every action is sampled from softmax(Q / kappa)."""

    kappa: float = option(0.1, "temperature of softmax(Q / kappa); also VDBE-Softmax's")

    def validate(self) -> None:
        check_positive(self, "kappa")


@dataclass
class MaxBoltzmannConfig:
    """Max-Boltzmann: greedy, or with probability epsilon a softmax(Q / kappa) sample."""

    epsilon: float = option(0.05, "probability of a softmax sample instead of the greedy action, in [0, 1]")
    kappa: float = option(0.1, "temperature of the softmax sample")

    def validate(self) -> None:
        check_probability(self, "epsilon")
        check_positive(self, "kappa")


class Softmax(ExplorationStrategy):
    """Every action sampled from softmax(Q / kappa)."""

    name = "softmax"

    def _epsilon(self) -> float:
        return 1.0

    def _kappa(self) -> float:
        return self.config.kappa


class MaxBoltzmann(ExplorationStrategy):
    """Greedy with probability 1 - epsilon, else a softmax(Q / kappa) sample."""

    name = "max_boltzmann"

    def _epsilon(self) -> float:
        return self.config.epsilon

    def _kappa(self) -> float:
        return self.config.kappa
