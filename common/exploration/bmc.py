"""epsilon-BMC: epsilon is the posterior mean weight of a uniform model against a greedy one.

``on_returns(g_greedy, g_uniform)``: one Bayesian update per transition, in order. The caller has
already applied (1 - terminal) to the bootstrap term (see ``greedy_and_uniform_returns``), so a
terminal transition's returns are just its reward. Which transitions of a batch the learner passes
is ``exploration.bmc.observations``: by default one per env step (``bmc_observation_count``,
``newest_transitions``), the authors' rate.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from common.exploration.base import ExplorationStrategy
from common.schema.fields import check, check_positive, option


BMC_OBSERVATIONS = ("per_step", "per_transition")


@dataclass
class BmcConfig:
    """epsilon-BMC: epsilon = alpha / (alpha + beta), a Beta posterior over a greedy and a uniform model."""

    alpha0: float = option(25.0, "alpha of the Beta prior (the uniform model's weight)")
    beta0: float = option(25.01, "beta of the Beta prior (the greedy model's weight); 25.01 is the authors' code, "
                                 "the paper says 25")
    a0: float = option(250.0, "shape a of the Normal-Gamma prior on the returns")
    b0: float = option(250.0, "rate b of the Normal-Gamma prior on the returns")
    mu0: float = option(0.0, "prior mean of the returns")
    tau0: float = option(1.0, "prior precision scale of the returns' mean")
    observations: str = option(
        "per_step", "which transitions of each batch the posterior observes: per_step (the authors' rate: as many "
                    "per update as env steps per update, the newest step of each trace first) or per_transition "
                    "(every unmasked transition of the batch: 30 per update, 7.5 per env step)",
        choices=BMC_OBSERVATIONS)

    def validate(self) -> None:
        check_positive(self, "alpha0", "beta0", "a0", "b0", "tau0")
        check(self.observations in BMC_OBSERVATIONS, "observations", f"must be one of {', '.join(BMC_OBSERVATIONS)}")


def greedy_and_uniform_returns(rewards: np.ndarray, next_q: np.ndarray, terminated: np.ndarray,
                               gamma: float) -> tuple[np.ndarray, np.ndarray]:
    """epsilon-BMC's two model returns per transition: G_Q bootstraps max Q(h', .), G_U mean Q(h', .).

    rewards and terminated have one shape S; next_q is S + (n_actions,). A
    terminated transition does not bootstrap (the authors' code omitted this).
    """
    rewards = np.asarray(rewards, dtype=np.float64)
    next_q = np.asarray(next_q, dtype=np.float64)
    continues = 1.0 - np.asarray(terminated, dtype=np.float64)
    if next_q.shape[:-1] != rewards.shape or continues.shape != rewards.shape:
        raise ValueError(f"rewards {rewards.shape}, next_q {next_q.shape} and terminated "
                         f"{continues.shape} do not describe the same transitions")
    g_greedy = rewards + gamma * continues * next_q.max(axis=-1)
    g_uniform = rewards + gamma * continues * next_q.mean(axis=-1)
    return g_greedy, g_uniform


def student_t_pdf(x: float, df: float, loc: float, scale: float) -> float:
    """Density of the location-scale Student-t distribution."""
    z = (x - loc) / scale
    log_density = (math.lgamma((df + 1.0) / 2.0) - math.lgamma(df / 2.0)
                   - 0.5 * math.log(df * math.pi) - math.log(scale)
                   - (df + 1.0) / 2.0 * math.log1p(z * z / df))
    return math.exp(log_density)


@dataclass(frozen=True)
class BmcPosterior:
    """Beta(alpha, beta) over the uniform model's weight, and Welford statistics of the returns G."""

    alpha: float
    beta: float
    count: int = 0
    mean: float = 0.0
    m2: float = 0.0  # sum of squared deviations from the mean

    @property
    def epsilon(self) -> float:
        return self.alpha / (self.alpha + self.beta)

    def validate(self) -> None:
        """What a posterior read from elsewhere must hold (bmc_update keeps it); floats are finite (record)."""
        check_positive(self, "alpha", "beta")
        check(self.count >= 0, "count", f"must be >= 0, got {self.count}")
        check(self.m2 >= 0, "m2", f"must be >= 0, got {self.m2}")

    @property
    def variance(self) -> float:
        return self.m2 / (self.count - 1) if self.count > 1 else 0.0


def bmc_update(posterior: BmcPosterior, g_greedy: float, g_uniform: float, config: BmcConfig) -> BmcPosterior:
    """One epsilon-BMC observation (docs/method.md, "epsilon-BMC", steps 2-6)."""
    alpha, beta = posterior.alpha, posterior.beta
    eps = posterior.epsilon
    g = (1.0 - eps) * g_greedy + eps * g_uniform
    count = posterior.count + 1
    mean = posterior.mean + (g - posterior.mean) / count
    m2 = posterior.m2 + (g - posterior.mean) * (g - mean)
    stats = dataclasses.replace(posterior, count=count, mean=mean, m2=m2)

    a = config.a0 + count / 2.0
    b = (config.b0 + count / 2.0 * stats.variance
         + count / 2.0 * config.tau0 / (config.tau0 + count) * (mean - config.mu0) ** 2)
    scale = math.sqrt(b / a)
    evidence_uniform = student_t_pdf(g, 2.0 * a, g_uniform, scale)
    evidence_greedy = student_t_pdf(g, 2.0 * a, g_greedy, scale)

    normaliser = evidence_uniform * alpha + evidence_greedy * beta
    if normaliser <= 0.0:
        return stats
    m = alpha / (alpha + beta + 1.0) * (evidence_uniform * (alpha + 1.0) + evidence_greedy * beta) / normaliser
    s = (alpha / (alpha + beta + 1.0) * (alpha + 1.0) / (alpha + beta + 2.0)
         * (evidence_uniform * (alpha + 2.0) + evidence_greedy * beta) / normaliser)
    r = (m - s) / (s - m * m)
    if not (math.isfinite(r) and r > 0.0):
        return stats  # rounding made the matched Beta degenerate; keep the previous one
    return dataclasses.replace(stats, alpha=m * r, beta=(1.0 - m) * r)


class EpsilonBmc(ExplorationStrategy):
    """epsilon-greedy whose epsilon is the posterior mean weight of the uniform model."""

    name = "bmc"
    needs_returns = True
    state_type = BmcPosterior

    def __init__(self, n_actions: int, config: BmcConfig) -> None:
        super().__init__(n_actions, config)
        self.posterior = BmcPosterior(alpha=config.alpha0, beta=config.beta0)

    def on_returns(self, g_greedy: np.ndarray, g_uniform: np.ndarray) -> None:
        greedy = np.asarray(g_greedy, dtype=np.float64).ravel()
        uniform = np.asarray(g_uniform, dtype=np.float64).ravel()
        if greedy.shape != uniform.shape or not (np.isfinite(greedy).all() and np.isfinite(uniform).all()):
            raise ValueError(f"g_greedy {greedy.shape} and g_uniform {uniform.shape} must be equal-sized and finite")
        super().on_returns(greedy, uniform)
        for g_q, g_u in zip(greedy.tolist(), uniform.tolist()):
            self.posterior = bmc_update(self.posterior, g_q, g_u, self.config)

    def _epsilon(self) -> float:
        return self.posterior.epsilon

    def own_state(self) -> BmcPosterior:
        return self.posterior

    def _restore(self, state: BmcPosterior) -> None:
        self.posterior = state


def bmc_observation_count(update: int, env_steps_per_update: float) -> int:
    """How many transitions the `update`-th update (1-based) feeds BMC at one per env step:
    floor(k * s) - floor((k - 1) * s), so k updates feed floor(k * s) in all."""
    return math.floor(update * env_steps_per_update) - math.floor((update - 1) * env_steps_per_update)


def newest_transitions(g_greedy: np.ndarray, g_uniform: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray]:
    """`count` transitions of a batch's (B, U) returns: the newest step of each trace first, then
    the one before it, and so on; kept in trace order, oldest first within a trace."""
    greedy, uniform = np.asarray(g_greedy), np.asarray(g_uniform)
    if greedy.shape != uniform.shape or greedy.ndim != 2:
        raise ValueError(f"g_greedy {greedy.shape} and g_uniform {uniform.shape} must be equal (B, U) arrays")
    traces, steps = greedy.shape
    count = max(0, min(count, greedy.size))
    rank = (steps - 1 - np.arange(steps))[None, :] * traces + np.arange(traces)[:, None]  # 0 = newest of trace 0
    chosen = rank < count
    return greedy[chosen], uniform[chosen]  # boolean indexing keeps row-major (trace, then time) order
