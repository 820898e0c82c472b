"""What every strategy shares: the (epsilon, kappa) action rule, the learner's hooks as no-ops, and the
state that travels to the actors and into checkpoints: typed (its config sections, its ``Counters``, its own
``state_type``), which the wire carries (common/wire/exploration_state.py), and as a plain dict in checkpoints."""

from __future__ import annotations

import dataclasses
import math
import typing
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from common.schema.fields import ConfigError, check, coerce


NO_TEMPERATURE = 0.0  # kappa of a strategy that explores uniformly


def softmax_probabilities(q_values: np.ndarray, kappa: float) -> np.ndarray:
    """softmax(Q / kappa), computed after subtracting max Q so that no exponent overflows."""
    q = np.asarray(q_values, dtype=np.float64)
    weights = np.exp((q - q.max()) / kappa)  # kappa = inf gives exp(0) = 1 everywhere
    return weights / weights.sum()


@dataclass(frozen=True)
class Counters:
    """What the learner's hooks counted: env steps seen, on_update calls, transitions passed to on_returns."""

    env_steps: int = 0
    updates: int = 0
    returns: int = 0

    def validate(self) -> None:
        for name in ("env_steps", "updates", "returns"):
            check(getattr(self, name) >= 0, name, f"must be >= 0, got {getattr(self, name)!r}")


@dataclass(frozen=True)
class NoState:
    """The own state of a strategy whose epsilon and kappa follow from its params and counters alone."""

    def validate(self) -> None:
        pass


def record(cls: type, values: Any, where: str) -> Any:
    """The dataclass cls (a config section, Counters, a strategy's state) from a plain map of its fields, each of
    its declared type (an int, a float: an int stands for one, finite; a string), then cls's own checks. A field
    with a default may be absent: a writer older than the field. ValueError (ConfigError) naming where and the field."""
    kinds = typing.get_type_hints(cls)
    names = [f.name for f in dataclasses.fields(cls)]
    if not isinstance(values, dict):
        raise ConfigError(f"{where}: expected a map of {', '.join(names) or 'no fields'}, got {type(values).__name__}")
    unknown = sorted(str(key) for key in values if key not in names)
    if unknown:
        raise ConfigError(f"{where}: {', '.join(unknown)} not among the fields of {cls.__name__} ({', '.join(names)})")
    typed = {}
    for name, value in values.items():
        if isinstance(value, str) and kinds[name] is not str:  # text converts in a config file, not on the wire
            raise ConfigError(f"{where}.{name}: expected a number, got {value!r}")
        typed[name] = coerce(f"{where}.{name}", kinds[name], value)
    try:
        instance = cls(**typed)
    except TypeError:
        missing = [f.name for f in dataclasses.fields(cls) if f.name not in values
                   and f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING]
        raise ConfigError(f"{where}: missing {', '.join(missing)}") from None
    try:
        instance.validate()
    except ConfigError as error:
        raise ConfigError(f"{where}.{error}") from None
    return instance


class ExplorationStrategy:
    """Base: the (epsilon, kappa) action rule, the learner's hooks as no-ops, and the state, typed and as a dict."""

    name = ""
    state_type: ClassVar[type] = NoState  # the strategy's own state, beside its counters (a frozen dataclass)
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

    def sections(self) -> tuple:
        """Its config sections, in its class's argument order (names.py): what it is rebuilt with."""
        return (self.config,)

    def params(self) -> dict:
        """Its sections' fields as one map, the form the wire and checkpoints write its params in."""
        return {name: value for section in self.sections() for name, value in dataclasses.asdict(section).items()}

    def counters(self) -> Counters:
        return Counters(self.env_steps, self.updates, self.returns)

    def own_state(self) -> Any:
        """Its own state, a state_type."""
        return NoState()

    def restore(self, started: bool, counters: Counters, state: Any) -> None:
        """Takes another instance's counters and own state (checked where they were read: the wire, record);
        epsilon and kappa are derived from them and the params, so they are not taken."""
        if type(state) is not self.state_type or type(counters) is not Counters or not isinstance(started, bool):
            raise ValueError(f"{self.name} restores from a bool, Counters and {self.state_type.__name__}, got "
                             f"{type(started).__name__}, {type(counters).__name__} and {type(state).__name__}")
        self._restore(state)
        self.started = started
        self.env_steps, self.updates, self.returns = counters.env_steps, counters.updates, counters.returns

    def state_dict(self) -> dict:
        """The checkpoint's form: plain values only."""
        return {
            "strategy": self.name,
            "params": self.params(),
            "epsilon": self.epsilon,
            "kappa": self.kappa,
            "started": self.started,
            "counters": dataclasses.asdict(self.counters()),
            "state": dataclasses.asdict(self.own_state()),
        }

    def load_state_dict(self, state: dict) -> None:
        """Loads another instance's state_dict() (a checkpoint's), each part checked before anything changes."""
        if not isinstance(state, dict) or not {"strategy", "params", "started", "counters", "state"} <= set(state):
            raise ValueError(f"malformed exploration state ({str(state)[:200]})")
        if state["strategy"] != self.name:
            raise ValueError(f"exploration state is for {state['strategy']!r}, this strategy is {self.name!r}")
        if state["params"] != self.params():
            raise ValueError(f"exploration params {state['params']} differ from this strategy's {self.params()}")
        if not isinstance(state["started"], bool):
            raise ValueError(f"exploration state 'started' must be true or false, got {state['started']!r}")
        self.restore(state["started"], record(Counters, state["counters"], "exploration.counters"),
                     record(self.state_type, state["state"], f"exploration.state ({self.name})"))

    def _epsilon(self) -> float:
        raise NotImplementedError

    def _kappa(self) -> float:
        return NO_TEMPERATURE

    def _restore(self, state: Any) -> None:
        pass
