"""The learner's exploration state on the wire, typed by the strategy it names (common/wire/exploration_state.py):
every strategy round trips and is rebuilt from the message alone (``follow``); what learners wrote before the
typed state, live or in a log, decodes into it; and a state made in this process is checked as the wire would."""

from __future__ import annotations

import dataclasses

import msgpack
import numpy as np
import pytest

from common.config import ExplorationConfig
from common.config_values import load_config
from common.exploration.base import Counters, NoState
from common.exploration.bmc import BmcConfig, BmcPosterior
from common.exploration.build import make_strategy
from common.exploration.names import STRATEGIES
from common.exploration.vdbe import VdbeConfig, VdbeState
from common.keys import Keys
from common.wire.envelope import SCHEMA_VERSION, decode, encode
from common.wire.errors import WireError
from common.wire.exploration_state import ExplorationState, exploration_message, follow
from replay.recorder.export import collect
from replay.recorder.reader import LogFile
from tests.test_exploration import moved
from tests.test_typed_metrics import write_log

N_ACTIONS = 5

# What a BMC learner sent before the typed state (its params, counters and state as maps), as its encoder wrote it.
OLD_BMC = {"strategy": "bmc", "params": {"alpha0": 30.0, "beta0": 25.01, "a0": 250.0, "b0": 250.0, "mu0": 0.0,
                                         "tau0": 1.0, "observations": "per_step"},
           "epsilon": 0.4, "kappa": 0.0, "started": True,
           "counters": {"env_steps": 12_000, "updates": 3_000, "returns": 12_000},
           "state": {"alpha": 20.0, "beta": 30.0, "count": 12_000, "mean": 4.5, "m2": 900.0}}


def old_payload(fields: dict) -> bytes:
    return msgpack.packb({"schema": SCHEMA_VERSION, "type": "ExplorationState", "fields": fields}, use_bin_type=True)


def worked(name: str, **settings) -> object:
    config = ExplorationConfig(strategy=name)
    config.vdbe.nu, config.softmax.kappa, config.bmc.alpha0 = 2.5, 0.3, 30.0  # not the defaults
    return moved(make_strategy(config, N_ACTIONS))


@pytest.mark.parametrize("name", STRATEGIES)
def test_every_strategy_is_rebuilt_from_its_decoded_state_alone(name):
    learner_side = worked(name)
    message = decode(encode(exploration_message(learner_side, start_by_steps=True)), ExplorationState)
    assert message.params == learner_side.sections() and message.state == learner_side.own_state()
    assert type(message.state) is learner_side.state_type and message.counters == learner_side.counters()
    assert message.start_by_steps is True
    actor_side = follow(None, message, N_ACTIONS)
    assert type(actor_side) is type(learner_side) and actor_side.state_dict() == learner_side.state_dict()
    assert all(a is not b for a, b in zip(actor_side.sections(), learner_side.sections()))  # nothing shared
    q_values = np.array([0.3, 0.1, 0.25, 0.0, 0.2])
    rngs = np.random.default_rng(5), np.random.default_rng(5)
    assert [actor_side.act(q_values, rngs[0]) for _ in range(200)] == [learner_side.act(q_values, rngs[1])
                                                                         for _ in range(200)]


def test_each_strategy_state_is_its_own_type():
    types = {name: make_strategy(ExplorationConfig(strategy=name), N_ACTIONS).state_type for name in STRATEGIES}
    assert types == {"constant": NoState, "decreasing": NoState, "softmax": NoState, "max_boltzmann": NoState,
                     "vdbe": VdbeState, "vdbe_softmax": VdbeState, "bmc": BmcPosterior}


def test_the_same_strategy_is_loaded_and_another_rebuilt():
    current = make_strategy(ExplorationConfig(strategy="vdbe"), N_ACTIONS)
    learner_side = worked("vdbe")  # nu 2.5: other params than current's
    rebuilt = follow(current, exploration_message(learner_side), N_ACTIONS)
    assert rebuilt is not current and rebuilt.params()["nu"] == 2.5 and not current.started
    loaded = follow(rebuilt, exploration_message(learner_side), N_ACTIONS)
    assert loaded is rebuilt and loaded.epsilon == learner_side.epsilon
    softmax = follow(rebuilt, exploration_message(worked("vdbe_softmax")), N_ACTIONS)
    assert softmax is not rebuilt and softmax.name == "vdbe_softmax"  # vdbe's params and more: another strategy


def test_a_learners_state_from_before_the_typed_state_decodes_into_it():
    message = decode(old_payload(OLD_BMC), ExplorationState)
    assert message.params == (BmcConfig(alpha0=30.0),) and message.counters == Counters(12_000, 3_000, 12_000)
    assert message.state == BmcPosterior(alpha=20.0, beta=30.0, count=12_000, mean=4.5, m2=900.0)
    assert message.start_by_steps is None  # it predates the field
    strategy = follow(None, message, N_ACTIONS)
    assert strategy.epsilon == 0.4 and strategy.started and strategy.returns == 12_000
    # one older still, from before bmc.observations: the setting takes its default
    params = {key: value for key, value in OLD_BMC["params"].items() if key != "observations"}
    assert decode(old_payload({**OLD_BMC, "params": params})).params == (BmcConfig(alpha0=30.0),)
    # and its wire form is the new one's: a reader of either sees the same bytes
    assert msgpack.unpackb(encode(message))["fields"] == {**OLD_BMC, "start_by_steps": None}


def test_a_log_recorded_before_the_typed_state_still_reads(tmp_path):
    config = load_config("smoke")
    key = Keys("d3rqn", config.run.name).exploration
    payloads = [old_payload(OLD_BMC), encode(exploration_message(worked("bmc")))]
    write_log(tmp_path / "log.mcap", config, key, payloads)
    with LogFile(tmp_path / "log.mcap") as log:
        read = [message for _, message in log.messages(ExplorationState)]
        rows = collect(log).exploration
    assert [type(message.state) for message in read] == [BmcPosterior, BmcPosterior]
    assert read[0].counters.updates == 3_000 and read[1].params == (BmcConfig(alpha0=30.0),)
    assert [row["counters.returns"] for row in rows] == [12_000, 3]
    assert rows[0]["strategy"] == "bmc" and rows[0]["epsilon"] == 0.4


@pytest.mark.parametrize("edit, error", [
    (lambda m: dataclasses.replace(m, state=VdbeState(0.5)), "expected a BmcPosterior, got VdbeState"),
    (lambda m: dataclasses.replace(m, state=BmcPosterior(alpha=float("nan"), beta=1.0)),
     "ExplorationState.state.alpha: expected a finite number"),
    (lambda m: dataclasses.replace(m, counters=Counters(env_steps=-4)), "ExplorationState.counters.env_steps: must be >= 0"),
    (lambda m: dataclasses.replace(m, params=(VdbeConfig(),)), "exploration param\\(s\\) eps0, lam, nu not among bmc's"),
    (lambda m: dataclasses.replace(m, params=BmcConfig()), "expected the 1 config section\\(s\\) of bmc"),
    (lambda m: dataclasses.replace(m, strategy="teleport"), "unknown exploration strategy 'teleport'"),
])
def test_a_state_made_in_this_process_is_checked_as_the_wire_would_and_changes_nothing(edit, error):
    current = follow(None, exploration_message(worked("bmc")), N_ACTIONS)
    before = current.state_dict()
    bad = edit(exploration_message(worked("bmc")))
    with pytest.raises(WireError, match=error):
        follow(current, bad, N_ACTIONS)
    with pytest.raises(WireError, match=error):
        encode(bad)
    assert current.state_dict() == before
