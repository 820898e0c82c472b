"""The deterministic epsilon-greedy strategies: constant epsilon, and decreasing epsilon, whose
schedule follows the env steps (``on_env_steps(total)``)."""

from __future__ import annotations

from dataclasses import dataclass

from common.exploration.base import ExplorationStrategy
from common.schema.fields import check, check_probability, option


@dataclass
class ConstantEpsilonConfig:
    """Constant epsilon-greedy."""

    epsilon: float = option(0.05, "probability of a uniformly random action, in [0, 1]")

    def validate(self) -> None:
        check_probability(self, "epsilon")


class ConstantEpsilonGreedy(ExplorationStrategy):
    name = "constant"

    def _epsilon(self) -> float:
        return self.config.epsilon


@dataclass
class DecreasingEpsilonConfig:
    """Decreasing epsilon-greedy: epsilon by env steps, two linear slopes (docs/method.md, "Decreasing
    epsilon-greedy")."""

    eps_start: float = option(1.0, "epsilon until n_start env steps, in [0, 1]")
    eps_last: float = option(0.1, "epsilon reached at n_start + n_ann env steps, the end of the first slope, "
                                  "in [0, 1]")
    eps_end: float = option(0.01, "epsilon reached at n_max env steps and held after, in [0, 1]")
    n_start: int = option(50_000, "env steps at eps_start before epsilon starts to fall", "env steps")
    n_ann: int = option(400_000, "length of the first slope, from eps_start to eps_last", "env steps")
    n_max: int = option(1_000_000, "end of the second slope, at eps_end; must exceed n_start + n_ann", "env steps")

    def validate(self) -> None:
        check_probability(self, "eps_start", "eps_last", "eps_end")
        check(self.n_start >= 0, "n_start", "must be >= 0")
        check(self.n_ann > 0, "n_ann", "must be > 0")
        check(self.n_max > self.n_start + self.n_ann, "n_max", "must exceed n_start + n_ann")


def decreasing_epsilon(env_steps: int, config: DecreasingEpsilonConfig) -> float:
    """The paper's two-slope schedule; held at eps_end after n_max."""
    pi_1 = -(config.eps_start - config.eps_last) / config.n_ann
    pi_0 = config.eps_start - pi_1 * config.n_start
    delta_1 = -(config.eps_last - config.eps_end) / (config.n_max - config.n_ann - config.n_start)
    delta_0 = config.eps_end - delta_1 * config.n_max
    if env_steps <= config.n_start:
        return config.eps_start
    if env_steps <= config.n_start + config.n_ann:
        return pi_0 + pi_1 * env_steps
    return max(config.eps_end, delta_0 + delta_1 * env_steps)


class DecreasingEpsilonGreedy(ExplorationStrategy):
    name = "decreasing"

    def _epsilon(self) -> float:
        return decreasing_epsilon(self.env_steps, self.config)
