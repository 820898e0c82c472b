"""The one registry of the seven exploration strategies: what each is called, its class and where its
settings live (the config sections its class is built with).

Every module that names or builds a strategy takes it from here: the config's choices, the
learner's exploration state, the replay's start rule, the grid's runs, the tables' and
figures' labels, and build.py. The classes are in the modules of common/exploration/, one per
rule, with their parameters.
"""

from __future__ import annotations

from dataclasses import dataclass

from common.exploration.base import ExplorationStrategy
from common.exploration.bmc import BmcConfig, EpsilonBmc
from common.exploration.boltzmann import MaxBoltzmann, MaxBoltzmannConfig, Softmax, SoftmaxConfig
from common.exploration.epsilon_greedy import (ConstantEpsilonConfig, ConstantEpsilonGreedy, DecreasingEpsilonConfig,
                                               DecreasingEpsilonGreedy)
from common.exploration.vdbe import Vdbe, VdbeConfig, VdbeSoftmax

# Each section of the config's exploration (exploration.<section>) and the dataclass that declares it.
SECTIONS = {"constant": ConstantEpsilonConfig, "decreasing": DecreasingEpsilonConfig, "vdbe": VdbeConfig,
            "bmc": BmcConfig, "softmax": SoftmaxConfig, "max_boltzmann": MaxBoltzmannConfig}


@dataclass(frozen=True)
class Strategy:
    name: str  # exploration.strategy, and the strategy an ExplorationState names
    display_name: str  # the paper's name, in tables and figures
    cls: type[ExplorationStrategy]  # built with n_actions and its sections, in order
    sections: tuple[str, ...]  # the exploration.<section> configs of its params, in its class's argument order
    epsilon_group: str | None  # the panel of the epsilon figure that draws it; None: it has no epsilon
    starts_by_steps: bool = False  # updates start at pace.start_steps env steps, not pace.start_episodes


REGISTRY = (
    Strategy("constant", "Constant ε-greedy", ConstantEpsilonGreedy, ("constant",), "deterministic epsilon-greedy"),
    Strategy("decreasing", "Decreasing ε-greedy", DecreasingEpsilonGreedy, ("decreasing",),
             "deterministic epsilon-greedy", starts_by_steps=True),
    Strategy("vdbe", "VDBE", Vdbe, ("vdbe",), "adaptive epsilon-greedy"),
    Strategy("bmc", "BMC", EpsilonBmc, ("bmc",), "adaptive epsilon-greedy"),
    Strategy("softmax", "Softmax", Softmax, ("softmax",), None),
    Strategy("max_boltzmann", "MBE", MaxBoltzmann, ("max_boltzmann",), "Max-Boltzmann"),
    Strategy("vdbe_softmax", "VDBE-Softmax", VdbeSoftmax, ("vdbe", "softmax"), "Max-Boltzmann"),
)
STRATEGIES = tuple(strategy.name for strategy in REGISTRY)
DISPLAY_NAMES = {strategy.name: strategy.display_name for strategy in REGISTRY}
_BY_NAME = {strategy.name: strategy for strategy in REGISTRY}


def strategy_named(name: str) -> Strategy:
    """The registry's entry; ValueError listing the choices for an unknown name."""
    try:
        return _BY_NAME[name]
    except (KeyError, TypeError):
        raise ValueError(f"unknown exploration strategy {name!r}; choose one of {', '.join(STRATEGIES)}") from None


def strategy_rank(name: str) -> int:
    """The registry's order (the paper's), which tables and figures follow; other names come after."""
    return STRATEGIES.index(name) if name in STRATEGIES else len(STRATEGIES)


def starts_by_steps(name: str, start_by: str = "strategy") -> bool:
    """Whether a run of this strategy starts updates by env steps rather than episodes, by pace.start_by:
    "strategy" is the paper's rule (decreasing epsilon by steps), "steps" and "episodes" hold for every strategy."""
    if start_by == "strategy":
        return strategy_named(name).starts_by_steps
    return start_by == "steps"


def epsilon_groups() -> dict[str, tuple[str, ...]]:
    """The strategies that have an epsilon, by group (the paper's families), in the registry's order."""
    groups: dict[str, tuple[str, ...]] = {}
    for strategy in REGISTRY:
        if strategy.epsilon_group is not None:
            groups[strategy.epsilon_group] = (*groups.get(strategy.epsilon_group, ()), strategy.name)
    return groups
