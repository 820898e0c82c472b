"""The learner's exploration state (the hub's exploration key), typed by the strategy it names: its params
are that strategy's config sections, its state that strategy's own ``state_type``, its counters Counters
(common/exploration/). Each is checked at the door by the strategy's own rules, so an actor rebuilds the
learner's strategy from the message alone (``follow``) and never from its own config.

The wire form is the one learners wrote before these types (params, counters and state as maps of plain
values), so their messages, and the logs that recorded them, decode into the typed message.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

from common.exploration.base import Counters, ExplorationStrategy, record
from common.exploration.build import sections_from_params, strategy_from
from common.exploration.names import strategy_named
from common.wire.codecs import (PROBABILITY, Codec, Dependent, Flag, Message, Nullable, Real, Text, _fail, pack_fields,
                                wired)
from common.wire.errors import WireError


@dataclass(frozen=True)
class Record(Codec):
    """A frozen dataclass that checks itself (``validate``), written as the map of its fields (``record``)."""

    cls: type

    def pack(self, value, where):
        if type(value) is not self.cls:
            raise _fail(where, f"expected a {self.cls.__name__}, got {type(value).__name__}")
        fields = dataclasses.asdict(value)
        self.unpack(fields, where)  # its checks, as a reader will make them
        return fields

    def unpack(self, raw, where):
        try:
            return record(self.cls, raw, where)
        except ValueError as error:  # record names where and the field
            raise WireError(str(error)) from None


@dataclass(frozen=True)
class Sections(Codec):
    """A strategy's config sections, in its class's order, written as its params in one map (the form
    ExplorationStrategy.params() gives and older learners wrote)."""

    strategy: str

    def pack(self, value, where):
        sections = strategy_named(self.strategy).sections
        if (not isinstance(value, tuple) or len(value) != len(sections)
                or not all(dataclasses.is_dataclass(section) for section in value)):
            raise _fail(where, f"expected the {len(sections)} config section(s) of {self.strategy} "
                               f"({', '.join(sections)}), got {type(value).__name__}")
        params = {name: item for section in value for name, item in dataclasses.asdict(section).items()}
        self.unpack(params, where)  # every section's checks, as a reader will make them
        return params

    def unpack(self, raw, where):
        try:
            return sections_from_params(self.strategy, raw)
        except (ValueError, TypeError) as error:
            raise _fail(where, str(error)) from None


def _named(values: dict[str, Any], where: str) -> str:
    name = values.get("strategy")
    try:
        strategy_named(name)
    except ValueError as error:
        raise _fail(where, str(error)) from None
    return name


@dataclass(frozen=True)
class StrategyParams(Dependent):
    def given(self, values, where):
        return Sections(_named(values, where))


@dataclass(frozen=True)
class StrategyState(Dependent):
    def given(self, values, where):
        return Record(strategy_named(_named(values, where)).cls.state_type)


@dataclass(eq=False)
class ExplorationState(Message):
    strategy: str = wired(Text())  # a name of the registry (common/exploration/names.py)
    params: tuple = wired(StrategyParams())  # its config sections, in its class's argument order
    epsilon: float = wired(PROBABILITY)
    kappa: float = wired(Real(min_value=0.0))  # 0 when the strategy has no temperature
    started: bool = wired(Flag())  # before updates start every strategy acts uniformly
    counters: Counters = wired(Record(Counters))
    state: Any = wired(StrategyState())  # the strategy's own state, its state_type
    # The learner's start rule (pace.start_by with its strategy), which the replay's rate limiter keeps:
    # updates start at pace.start_steps env steps (True) or pace.start_episodes episodes (False).
    # None: a learner that predates the field; the replay then derives it from the strategy's name.
    start_by_steps: bool | None = wired(Nullable(Flag()), default=None)


def exploration_message(strategy: ExplorationStrategy, start_by_steps: bool | None = None) -> ExplorationState:
    """The strategy's state as the message the actors follow, with the learner's start rule for the replay.
    The sections are copies: a reader that rebuilds the strategy from them shares nothing with the sender."""
    return ExplorationState(strategy=strategy.name, params=tuple(dataclasses.replace(s) for s in strategy.sections()),
                            epsilon=strategy.epsilon, kappa=strategy.kappa, started=strategy.started,
                            counters=strategy.counters(), state=strategy.own_state(), start_by_steps=start_by_steps)


def follow(current: ExplorationStrategy | None, message: ExplorationState, n_actions: int) -> ExplorationStrategy:
    """The strategy the learner's state describes: `current` loaded with it when it is the same strategy with
    the same params, else one rebuilt from the message alone. A message made in this process, which no
    decode checked, is checked as the wire would; WireError (a ValueError) and nothing changed if it fails."""
    pack_fields(message, "ExplorationState")
    if current is not None and current.name == message.strategy and current.sections() == message.params:
        strategy = current
    else:
        strategy = strategy_from(message.strategy, message.params, n_actions)
    strategy.restore(message.started, message.counters, message.state)
    return strategy
