"""What every strategy shares: the (epsilon, kappa) action rule, the learner's hooks as no-ops, and the
state that travels to the actors and into checkpoints."""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np


NO_TEMPERATURE = 0.0  # kappa of a strategy that explores uniformly


def softmax_probabilities(q_values: np.ndarray, kappa: float) -> np.ndarray:
    """softmax(Q / kappa), computed after subtracting max Q so that no exponent overflows."""
    q = np.asarray(q_values, dtype=np.float64)
    weights = np.exp((q - q.max()) / kappa)  # kappa = inf gives exp(0) = 1 everywhere
    return weights / weights.sum()


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


def state_positive(state: dict, key: str) -> float:
    value = float(state[key])
    if not (math.isfinite(value) and value > 0):
        raise ValueError(f"exploration state {key} must be a positive number, got {state[key]!r}")
    return value


def state_probability(state: dict, key: str) -> float:
    value = float(state[key])
    if not 0.0 <= value <= 1.0:
        raise ValueError(f"exploration state {key} must lie in [0, 1], got {state[key]!r}")
    return value
