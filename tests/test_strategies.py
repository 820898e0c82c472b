"""The registry of strategy names (common/exploration/names.py) agrees with the config, the classes and
the tables that use it."""

import dataclasses

import pytest

from common.analysis.figures import EPSILON_STRATEGIES
from common.config import ExplorationConfig
from common.config_values import load_config
from common.exploration.build import make_strategy
from common.exploration.names import SECTIONS as SECTION_CLASSES
from common.exploration.names import (REGISTRY, STRATEGIES, epsilon_groups, starts_by_steps, strategy_named,
                                      strategy_rank)
from common.schema.fields import ConfigError
from deploy.studies.comparison import STRATEGY_NAMES

SECTIONS = {field.name for field in dataclasses.fields(ExplorationConfig)} - {"strategy"}


def test_the_seven_strategies_have_one_entry_each_with_a_display_name():
    assert len(STRATEGIES) == len(set(STRATEGIES)) == 7
    assert all(strategy.display_name and strategy.display_name != strategy.name for strategy in REGISTRY)
    assert len({strategy.display_name for strategy in REGISTRY}) == 7
    assert set(STRATEGY_NAMES) == {*STRATEGIES, "random", "privileged"}  # and the baselines


def test_tables_and_figures_follow_the_registrys_order_and_put_other_names_last():
    assert sorted(["softmax", "random", "constant", "vdbe_softmax"], key=strategy_rank) == [
        "constant", "softmax", "vdbe_softmax", "random"]


def test_every_strategy_has_config_sections_and_every_section_a_strategy():
    assert all(strategy.sections and set(strategy.sections) <= SECTIONS for strategy in REGISTRY)
    assert {section for strategy in REGISTRY for section in strategy.sections} == SECTIONS


def test_the_registrys_section_classes_are_the_configs():
    """A strategy rebuilt from the learner's state (build.py) takes its sections from the registry: the very
    dataclasses the config declares."""
    config = ExplorationConfig()
    assert {name: type(getattr(config, name)) for name in SECTIONS} == SECTION_CLASSES


@pytest.mark.parametrize("name", STRATEGIES)
def test_each_name_builds_its_class_with_the_params_of_its_sections(name):
    config = ExplorationConfig(strategy=name)
    policy = make_strategy(config, 5)
    assert type(policy) is strategy_named(name).cls and policy.name == name
    expected = {key: value for section in strategy_named(name).sections
                for key, value in dataclasses.asdict(getattr(config, section)).items()}
    assert policy.params() == expected


def test_only_softmax_has_no_epsilon_and_only_decreasing_starts_by_steps():
    assert set(EPSILON_STRATEGIES) == set(STRATEGIES) - {"softmax"}
    assert sum(epsilon_groups().values(), ()) == EPSILON_STRATEGIES
    assert [name for name in STRATEGIES if starts_by_steps(name)] == ["decreasing"]
    assert [name for name in STRATEGIES if starts_by_steps(name, "strategy")] == ["decreasing"]


def test_a_start_rule_other_than_the_strategys_holds_for_every_strategy():
    assert all(starts_by_steps(name, "steps") for name in STRATEGIES)
    assert not any(starts_by_steps(name, "episodes") for name in STRATEGIES)


def test_an_unknown_strategy_is_refused_with_the_choices():
    with pytest.raises(ConfigError, match="exploration.strategy: must be one of " + ", ".join(STRATEGIES)):
        load_config("smoke", overrides={"exploration.strategy": "greedy"})
    with pytest.raises(ValueError, match="unknown exploration strategy 'greedy'; choose one of constant, "):
        strategy_named("greedy")
