"""The paper's seven exploration strategies, as small classes the actor and the learner share, each
next to its parameters (its section of the config, exploration.<section>).

Every strategy is a Max-Boltzmann rule with two numbers: with probability
``epsilon`` it explores, otherwise it takes the greedy action. Exploring samples
softmax(Q / kappa), or, when ``kappa`` is 0 ("no temperature", as the wire's
ExplorationState has it), a uniform action: the epsilon-greedy family is
(epsilon, 0), Softmax is (1, kappa) and Max-Boltzmann is (epsilon, kappa).
Until ``start()`` (updates start) every strategy is (1, 0): uniform random
actions.

The actor only calls ``act``. The learner calls the hooks and sends
``state_dict()`` to the actors, which ``load_state_dict`` it:

- ``on_env_steps(total)``: the step-based schedule of decreasing epsilon-greedy.
- ``on_update(q_before, q_after)``: VDBE. Q(h, a*) of the same histories and
  greedy actions a* (greedy under the weights before the update), under the
  weights before and after one gradient step. A batch gives one Delta per
  history; the paper's rule updates epsilon once per network update, so this
  does it once per call with f averaged over the batch:
  eps <- lambda * mean_i f(Delta_i) + (1 - lambda) * eps. Averaging f (not
  Delta) keeps each history's contribution bounded by 1, as in the tabular rule.
- ``on_returns(g_greedy, g_uniform)``: epsilon-BMC. One Bayesian update per
  transition, in order. The caller has already applied (1 - terminal) to the
  bootstrap term (see ``greedy_and_uniform_returns``), so a terminal
  transition's returns are just its reward. Which transitions of a batch the
  learner passes is ``exploration.bmc.observations``: by default one per env
  step (``bmc_observation_count``, ``newest_transitions``), the authors' rate.

The learner is the authority on the strategy: an actor whose own config names
another strategy or other params rebuilds its strategy from the learner's
state (``strategy_from_state``).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from common.options import check, check_positive, check_probability, option
from common.strategies import strategy_named
from common.wire.messages import ExplorationState

if TYPE_CHECKING:  # common/config.py imports this module: the annotation only
    from common.config import ExplorationConfig

NO_TEMPERATURE = 0.0  # kappa of a strategy that explores uniformly


# --- the formulas, as pure functions -----------------------------------------------

def softmax_probabilities(q_values: np.ndarray, kappa: float) -> np.ndarray:
    """softmax(Q / kappa), computed after subtracting max Q so that no exponent overflows."""
    q = np.asarray(q_values, dtype=np.float64)
    weights = np.exp((q - q.max()) / kappa)  # kappa = inf gives exp(0) = 1 everywhere
    return weights / weights.sum()


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


def vdbe_f(delta: np.ndarray | float, nu: float) -> np.ndarray:
    """f = (1 - e^(-|Delta|/nu)) / (1 + e^(-|Delta|/nu)), in [0, 1)."""
    decay = np.exp(-np.abs(delta) / nu)
    return (1.0 - decay) / (1.0 + decay)


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


# --- the strategies ---------------------------------------------------------------------

class ExplorationStrategy:
    """Base: the (epsilon, kappa) action rule, the learner's hooks as no-ops, and the state dict."""

    name = ""
    needs_q_after = False  # the learner must compute Q(h, a*) after each update (VDBE)
    needs_returns = False  # the learner must pass G_Q and G_U (BMC)

    def __init__(self, n_actions: int, config: Any) -> None:
        if n_actions < 1:
            raise ValueError(f"n_actions must be >= 1, got {n_actions}")
        self.n_actions = n_actions
        self.config = config  # the strategy's section of ExplorationConfig
        self.started = False
        self.env_steps = 0
        self.updates = 0  # on_update calls
        self.returns = 0  # transitions passed to on_returns

    # actor side

    @property
    def epsilon(self) -> float:
        """Probability of an exploring action (1 before start)."""
        return self._epsilon() if self.started else 1.0

    @property
    def kappa(self) -> float:
        """Softmax temperature of exploring actions; 0 means none: they are uniform (before start, epsilon-greedy)."""
        return self._kappa() if self.started else NO_TEMPERATURE

    def act(self, q_values: np.ndarray, rng: np.random.Generator) -> int:
        q = np.asarray(q_values, dtype=np.float64)
        if q.shape != (self.n_actions,) or not np.isfinite(q).all():
            raise ValueError(f"q_values must be {self.n_actions} finite numbers, got {q_values!r}")
        if rng.random() < self.epsilon:
            temperature = self.kappa if self.kappa > 0 else math.inf  # an infinite temperature is uniform
            return int(rng.choice(self.n_actions, p=softmax_probabilities(q, temperature)))
        return int(np.argmax(q))

    # learner side

    def start(self) -> None:
        self.started = True

    def on_env_steps(self, total_env_steps: int) -> None:
        self.env_steps = int(total_env_steps)

    def on_update(self, q_before: np.ndarray, q_after: np.ndarray) -> None:
        self.updates += 1

    def on_returns(self, g_greedy: np.ndarray, g_uniform: np.ndarray) -> None:
        self.returns += np.asarray(g_greedy).size

    # wire and checkpoint

    def params(self) -> dict:
        return dataclasses.asdict(self.config)

    def state_dict(self) -> dict:
        return {
            "strategy": self.name,
            "params": self.params(),
            "epsilon": self.epsilon,
            "kappa": self.kappa,
            "started": self.started,
            "counters": {"env_steps": self.env_steps, "updates": self.updates, "returns": self.returns},
            "state": self._state(),
        }

    def load_state_dict(self, state: dict) -> None:
        """Loads another instance's state_dict(); epsilon and kappa are derived, so they are not read."""
        try:
            if state["strategy"] != self.name:
                raise ValueError(f"exploration state is for {state['strategy']!r}, this strategy is {self.name!r}")
            if state["params"] != self.params():
                raise ValueError(f"exploration params {state['params']} differ from this strategy's {self.params()}")
            counters = state["counters"]
            env_steps, updates, returns = int(counters["env_steps"]), int(counters["updates"]), int(counters["returns"])
            started = state["started"]
            if not isinstance(started, bool):
                raise ValueError(f"exploration state 'started' must be true or false, got {started!r}")
            self._load_state(state["state"])  # validates before it changes anything
        except (KeyError, TypeError) as error:
            raise ValueError(f"malformed exploration state ({error!r})") from None
        self.started = started
        self.env_steps, self.updates, self.returns = env_steps, updates, returns

    def _epsilon(self) -> float:
        raise NotImplementedError

    def _kappa(self) -> float:
        return NO_TEMPERATURE

    def _state(self) -> dict:
        return {}

    def _load_state(self, state: dict) -> None:
        if state:
            raise ValueError(f"{self.name} keeps no state, got {state}")


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


class DecreasingEpsilonGreedy(ExplorationStrategy):
    name = "decreasing"

    def _epsilon(self) -> float:
        return decreasing_epsilon(self.env_steps, self.config)


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


class Vdbe(ExplorationStrategy):
    """Value-difference based exploration: epsilon follows how much an update moves Q(h, a*)."""

    name = "vdbe"
    needs_q_after = True

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

    def _state(self) -> dict:
        return {"epsilon": self._eps}

    def _load_state(self, state: dict) -> None:
        self._eps = _probability(state, "epsilon")


class VdbeSoftmax(Vdbe):
    """Max-Boltzmann exploration whose epsilon follows the VDBE rule."""

    name = "vdbe_softmax"

    def __init__(self, n_actions: int, config: VdbeConfig, softmax: SoftmaxConfig) -> None:
        super().__init__(n_actions, config)
        self.softmax = softmax

    def params(self) -> dict:
        return {**dataclasses.asdict(self.config), **dataclasses.asdict(self.softmax)}

    def _kappa(self) -> float:
        return self.softmax.kappa


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


class EpsilonBmc(ExplorationStrategy):
    """epsilon-greedy whose epsilon is the posterior mean weight of the uniform model."""

    name = "bmc"
    needs_returns = True

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

    def _state(self) -> dict:
        return dataclasses.asdict(self.posterior)

    def _load_state(self, state: dict) -> None:
        alpha, beta = _positive(state, "alpha"), _positive(state, "beta")
        count, mean, m2 = int(state["count"]), float(state["mean"]), float(state["m2"])
        if count < 0 or m2 < 0 or not math.isfinite(mean + m2):
            raise ValueError(f"bmc running statistics are invalid: {state}")
        self.posterior = BmcPosterior(alpha, beta, count, mean, m2)


@dataclass
class SoftmaxConfig:
    """Softmax (Boltzmann) exploration: every action is sampled from softmax(Q / kappa)."""

    kappa: float = option(0.1, "temperature of softmax(Q / kappa); also VDBE-Softmax's")

    def validate(self) -> None:
        check_positive(self, "kappa")


class Softmax(ExplorationStrategy):
    """Every action sampled from softmax(Q / kappa)."""

    name = "softmax"

    def _epsilon(self) -> float:
        return 1.0

    def _kappa(self) -> float:
        return self.config.kappa


@dataclass
class MaxBoltzmannConfig:
    """Max-Boltzmann: greedy, or with probability epsilon a softmax(Q / kappa) sample."""

    epsilon: float = option(0.05, "probability of a softmax sample instead of the greedy action, in [0, 1]")
    kappa: float = option(0.1, "temperature of the softmax sample")

    def validate(self) -> None:
        check_probability(self, "epsilon")
        check_positive(self, "kappa")


class MaxBoltzmann(ExplorationStrategy):
    """Greedy with probability 1 - epsilon, else a softmax(Q / kappa) sample."""

    name = "max_boltzmann"

    def _epsilon(self) -> float:
        return self.config.epsilon

    def _kappa(self) -> float:
        return self.config.kappa


# One class per name of common.strategies, built from that name's config sections.
STRATEGY_CLASSES = {cls.name: cls for cls in (ConstantEpsilonGreedy, DecreasingEpsilonGreedy, Vdbe, EpsilonBmc,
                                              Softmax, MaxBoltzmann, VdbeSoftmax)}


def same_strategy(strategy: ExplorationStrategy, state: dict) -> bool:
    """Whether a state_dict() describes this strategy with these params."""
    return state.get("strategy") == strategy.name and state.get("params") == strategy.params()


def strategy_from_state(state: dict, n_actions: int) -> ExplorationStrategy:
    """The strategy another process's state_dict() describes, built from its name and params
    (not from the local config) and loaded with its state; ValueError if it cannot be."""
    from common.config import Config  # the full config checks every value
    from common.config_values import set_value
    from common.options import ConfigError

    try:
        name, params = state["strategy"], state["params"]
        sections = strategy_named(name).sections
    except (KeyError, TypeError, ValueError):
        raise ValueError(f"exploration state names no known strategy ({str(state)[:200]})") from None
    if not isinstance(params, dict):
        raise ValueError(f"exploration params must be a map, got {params!r}")
    config = Config()
    config.exploration.strategy = name
    owners = {f.name: section for section in sections
              for f in dataclasses.fields(getattr(config.exploration, section))}
    try:
        for key, value in params.items():
            if key not in owners:
                raise ValueError(f"exploration param {key!r} is not one of {name}'s ({', '.join(sorted(owners))})")
            set_value(config, f"exploration.{owners[key]}.{key}", value)
        for section in sections:
            getattr(config.exploration, section).validate()
    except ConfigError as error:
        raise ValueError(f"exploration params: {error}") from None
    strategy = make_strategy(config.exploration, n_actions)
    strategy.load_state_dict(state)
    return strategy


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


def make_strategy(config: ExplorationConfig, n_actions: int) -> ExplorationStrategy:
    """The strategy named by config.strategy, with its sections of the config."""
    sections = strategy_named(config.strategy).sections
    return STRATEGY_CLASSES[config.strategy](n_actions, *(getattr(config, section) for section in sections))


def _positive(state: dict, key: str) -> float:
    value = float(state[key])
    if not (math.isfinite(value) and value > 0):
        raise ValueError(f"exploration state {key} must be a positive number, got {state[key]!r}")
    return value


def _probability(state: dict, key: str) -> float:
    value = float(state[key])
    if not 0.0 <= value <= 1.0:
        raise ValueError(f"exploration state {key} must lie in [0, 1], got {state[key]!r}")
    return value


def exploration_message(strategy: ExplorationStrategy) -> ExplorationState:
    """The strategy's state_dict() as the wire message the actors load."""
    return ExplorationState(**strategy.state_dict())
