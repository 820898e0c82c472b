import math
import warnings

import numpy as np
import pytest
import scipy.stats

from common.config import ExplorationConfig
from common.exploration.base import Counters, record, softmax_probabilities
from common.exploration.bmc import (BmcConfig, BmcPosterior, EpsilonBmc, bmc_observation_count,
                                    greedy_and_uniform_returns, newest_transitions, student_t_pdf)
from common.exploration.boltzmann import MaxBoltzmann, MaxBoltzmannConfig, SoftmaxConfig
from common.exploration.build import make_strategy, sections_from_params, strategy_from
from common.exploration.epsilon_greedy import (ConstantEpsilonConfig, DecreasingEpsilonConfig, DecreasingEpsilonGreedy,
                                               decreasing_epsilon)
from common.exploration.names import STRATEGIES
from common.exploration.vdbe import VdbeConfig, VdbeState, vdbe_f
from common.schema.fields import ConfigError

N_ACTIONS = 5


def strategy(name: str, n_actions: int = N_ACTIONS):
    return make_strategy(ExplorationConfig(strategy=name), n_actions)


def action_counts(policy, q_values, draws: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    actions = [policy.act(np.asarray(q_values), rng) for _ in range(draws)]
    return np.bincount(actions, minlength=len(q_values))


def assert_frequencies(counts: np.ndarray, probabilities, significance: float = 1e-3) -> None:
    """Chi-square goodness of fit; the seed is fixed, so the outcome is too."""
    expected = counts.sum() * np.asarray(probabilities)
    observed, expected = counts[expected > 0], expected[expected > 0]
    assert counts[np.asarray(probabilities) == 0].sum() == 0
    assert scipy.stats.chisquare(observed, expected).pvalue > significance, (counts, expected)


# --- every strategy ------------------------------------------------------------------

def test_the_factory_knows_every_configured_strategy():
    assert [strategy(name).name for name in STRATEGIES] == list(STRATEGIES)
    assert {name for name in STRATEGIES if strategy(name).needs_q_after} == {"vdbe", "vdbe_softmax"}
    assert {name for name in STRATEGIES if strategy(name).needs_returns} == {"bmc"}


@pytest.mark.parametrize("name", STRATEGIES)
def test_uniform_random_before_updates_start(name):
    policy = strategy(name)
    policy.on_env_steps(900_000)  # decreasing epsilon would be 0.0245 here, were it started
    assert policy.epsilon == 1.0 and policy.kappa == 0.0
    counts = action_counts(policy, [50.0, 0.0, -1.0, 3.0, 0.0], draws=5_000, seed=1)
    assert_frequencies(counts, [0.2] * 5)


def moved(policy):
    """The policy started and past 300,000 env steps, with one update and one return seen where it uses them:
    a state away from its initial one."""
    policy.start()
    policy.on_env_steps(300_000)
    if policy.needs_q_after:
        policy.on_update(np.array([1.0, 2.0, 3.0]), np.array([1.5, 1.0, 3.0]))
    if policy.needs_returns:
        policy.on_returns(np.array([1.2, 0.3, 2.0]), np.array([0.8, 0.1, 1.0]))
    return policy


@pytest.mark.parametrize("name", STRATEGIES)
def test_state_dict_round_trips_through_a_checkpoint(name):
    policy = moved(strategy(name))
    state = policy.state_dict()
    copy = strategy(name)
    copy.load_state_dict(copy_of_plain(state))
    assert copy.state_dict() == state and copy.own_state() == policy.own_state()
    assert (copy.epsilon, copy.kappa, copy.started) == (policy.epsilon, policy.kappa, True)
    q_values = np.array([0.3, 0.1, 0.25, 0.0, 0.2])
    assert (action_counts(copy, q_values, 300, seed=5) == action_counts(policy, q_values, 300, seed=5)).all()


def copy_of_plain(state: dict) -> dict:
    """A state_dict() as a checkpoint file gives it back: plain values, nothing shared with the strategy."""
    return {key: dict(value) if isinstance(value, dict) else value for key, value in state.items()}


def test_state_dict_holds_the_wire_fields():
    state = strategy("bmc").state_dict()
    assert set(state) == {"strategy", "params", "epsilon", "kappa", "started", "counters", "state"}
    assert state["params"] == {"alpha0": 25.0, "beta0": 25.01, "a0": 250.0, "b0": 250.0, "mu0": 0.0, "tau0": 1.0,
                               "observations": "per_step"}
    assert state["state"] == {"alpha": 25.0, "beta": 25.01, "count": 0, "mean": 0.0, "m2": 0.0}
    assert state["counters"] == {"env_steps": 0, "updates": 0, "returns": 0}


def test_a_checkpoint_written_before_the_typed_state_still_loads():
    """The exploration part of a checkpoint as learners wrote it before the typed state, as literal values."""
    saved = {"strategy": "vdbe", "params": {"lam": 0.2, "nu": 1.0, "eps0": 1.0}, "epsilon": 0.35, "kappa": 0.0,
             "started": True, "counters": {"env_steps": 40_000, "updates": 9_000, "returns": 0},
             "state": {"epsilon": 0.35}}
    policy = strategy("vdbe")
    policy.load_state_dict(saved)
    assert policy.own_state() == VdbeState(0.35) and policy.epsilon == 0.35 and policy.started
    assert policy.counters() == Counters(env_steps=40_000, updates=9_000, returns=0)
    assert policy.state_dict() == saved


def test_loading_a_wrong_state_is_a_value_error_and_changes_nothing():
    policy = strategy("vdbe")
    good = strategy("vdbe").state_dict()
    bad_states = [
        ({**good, "strategy": "bmc"}, "is for 'bmc'"),
        ({**good, "params": {**good["params"], "nu": 2.0}}, "differ"),
        ({**good, "state": {"epsilon": 1.5}}, r"exploration.state \(vdbe\).epsilon: must lie in \[0, 1\]"),
        ({**good, "state": {"epsilon": "0.5"}}, "expected a number"),
        ({**good, "started": "yes"}, "true or false"),
        ({**good, "counters": {**good["counters"], "updates": -1}}, "exploration.counters.updates: must be >= 0"),
        ({key: value for key, value in good.items() if key != "counters"}, "malformed"),
        ({**good, "state": {}}, r"exploration.state \(vdbe\): missing epsilon"),
        ("not a dict", "malformed"),
    ]
    for state, message in bad_states:
        with pytest.raises(ValueError, match=message):
            policy.load_state_dict(state)
    assert policy.state_dict() == good


def test_restore_takes_only_typed_parts_of_its_own_strategy():
    policy = strategy("vdbe")
    with pytest.raises(ValueError, match="vdbe restores from a bool, Counters and VdbeState, got bool, Counters and "
                                         "BmcPosterior"):
        policy.restore(True, Counters(), BmcPosterior(alpha=1.0, beta=1.0))
    with pytest.raises(ValueError, match="got bool, dict and VdbeState"):
        policy.restore(True, {"env_steps": 1}, VdbeState(0.5))
    assert policy.state_dict() == strategy("vdbe").state_dict()


def test_a_strategy_without_state_refuses_one_by_name():
    state = strategy("constant").state_dict()
    with pytest.raises(ValueError, match=r"^exploration.state \(constant\): epsilon not among the fields of NoState "
                                         r"\(\)$"):
        strategy("constant").load_state_dict({**state, "state": {"epsilon": 0.5}})


# --- a strategy from another process's params (actors follow the learner) -----------------

@pytest.mark.parametrize("name", STRATEGIES)
def test_a_strategy_is_rebuilt_from_its_params_alone(name):
    config = ExplorationConfig(strategy=name)
    config.vdbe.nu, config.softmax.kappa, config.bmc.alpha0 = 2.5, 0.3, 30.0  # not the defaults
    learner_side = make_strategy(config, N_ACTIONS)
    sections = sections_from_params(name, learner_side.params())
    assert sections == learner_side.sections() and all(a is not b for a, b in zip(sections, learner_side.sections()))
    rebuilt = strategy_from(name, sections, N_ACTIONS)
    assert type(rebuilt) is type(learner_side) and rebuilt.params() == learner_side.params()


def test_params_that_cannot_be_followed_are_a_value_error():
    good = strategy("vdbe").params()
    for name, params, message in [
            ("greedy", good, "unknown exploration strategy 'greedy'"),
            ("vdbe", {**good, "kappa": 0.1}, r"^exploration param\(s\) kappa not among vdbe's \(eps0, lam, nu\)$"),
            ("vdbe", {**good, "lam": 2.0}, r"exploration.vdbe.lam: must lie in \[0, 1\], got 2.0"),
            ("vdbe", {**good, "nu": "x"}, "exploration.vdbe.nu: expected a number, got 'x'"),
            ("vdbe", {**good, "nu": math.inf}, "exploration.vdbe.nu: expected a finite number"),
            ("vdbe", [1], "must be a map, got list")]:
        with pytest.raises(ValueError, match=message):
            sections_from_params(name, params)
    with pytest.raises(ValueError, match="vdbe_softmax is built with sections vdbe, softmax, got VdbeConfig$"):
        strategy_from("vdbe_softmax", (VdbeConfig(),), N_ACTIONS)


def test_params_a_writer_older_than_a_setting_left_out_take_its_default():
    params = {key: value for key, value in strategy("bmc").params().items() if key != "observations"}
    assert sections_from_params("bmc", params) == (BmcConfig(),)


def test_state_values_are_checked_at_their_bounds():
    # Found by mutation testing: each bound from both sides, and the refusal names the key
    assert record(BmcPosterior, {"alpha": 0.5, "beta": 0.5}, "s").alpha == 0.5  # positive, below 1: taken
    for bad in (0.0, -1.0):
        with pytest.raises(ValueError, match=f"^s.alpha: must be > 0, got {bad!r}$"):
            record(BmcPosterior, {"alpha": bad, "beta": 1.0}, "s")
    for bad in (math.inf, math.nan):
        with pytest.raises(ValueError, match="^s.alpha: expected a finite number"):
            record(BmcPosterior, {"alpha": bad, "beta": 1.0}, "s")
    assert record(VdbeState, {"epsilon": 0.0}, "s") == VdbeState(0.0)  # both ends of [0, 1] are probabilities
    assert record(VdbeState, {"epsilon": 1}, "s") == VdbeState(1.0)  # an int stands for a float
    for bad in (-0.01, 1.01):
        with pytest.raises(ValueError, match="must lie in"):
            record(VdbeState, {"epsilon": bad}, "s")


def test_bmc_loads_a_fresh_posterior_and_refuses_impossible_statistics():
    fresh = strategy("bmc").state_dict()
    assert fresh["state"]["count"] == 0 and fresh["state"]["m2"] == 0.0
    policy = strategy("bmc")
    policy.load_state_dict(fresh)  # no observation yet: count 0 and m2 0 are the start, not an error
    assert policy.state_dict() == fresh
    one = {**fresh, "state": {**fresh["state"], "count": 1, "mean": 2.0}}  # one observation: m2 still 0
    policy.load_state_dict(one)
    assert policy.posterior.count == 1
    for bad, message in (({"count": -1}, "count: must be >= 0"), ({"m2": -1.0}, "m2: must be >= 0"),
                         ({"mean": math.inf}, "mean: expected a finite number"),
                         ({"m2": math.nan}, "m2: expected a finite number"), ({"count": 1.5}, "expected an integer")):
        with pytest.raises(ValueError, match=message):
            policy.load_state_dict({**fresh, "state": {**fresh["state"], **bad}})
    assert policy.posterior.count == 1


@pytest.mark.parametrize("section, key, bad, message", [
    (ConstantEpsilonConfig, "epsilon", 1.5, "must lie in [0, 1], got 1.5"),
    (DecreasingEpsilonConfig, "eps_start", -0.1, "must lie in [0, 1], got -0.1"),
    (DecreasingEpsilonConfig, "eps_last", 1.1, "must lie in [0, 1], got 1.1"),
    (DecreasingEpsilonConfig, "eps_end", 2.0, "must lie in [0, 1], got 2.0"),
    (DecreasingEpsilonConfig, "n_start", -1, "must be >= 0"),
    (DecreasingEpsilonConfig, "n_ann", 0, "must be > 0"),
    (DecreasingEpsilonConfig, "n_max", 450_000, "must exceed n_start + n_ann"),  # equal to it: refused
    (SoftmaxConfig, "kappa", 0.0, "must be > 0, got 0.0"),
    (MaxBoltzmannConfig, "epsilon", -0.5, "must lie in [0, 1], got -0.5"),
    (MaxBoltzmannConfig, "kappa", -1.0, "must be > 0, got -1.0"),
    (VdbeConfig, "lam", 1.5, "must lie in [0, 1], got 1.5"),
    (VdbeConfig, "eps0", -1.0, "must lie in [0, 1], got -1.0"),
    (VdbeConfig, "nu", 0.0, "must be > 0, got 0.0"),
    *[(BmcConfig, key, 0.0, "must be > 0, got 0.0") for key in ("alpha0", "beta0", "a0", "b0", "tau0")],
    (BmcConfig, "observations", "per_episode", "must be one of per_step, per_transition"),
])
def test_each_strategy_setting_out_of_range_is_refused_by_its_name(section, key, bad, message):
    # Found by mutation testing: a setting left out of its check, or a refusal that names no key,
    # passed every test that builds strategies from valid settings
    settings = section()
    settings.validate()  # the defaults are valid
    setattr(settings, key, bad)
    with pytest.raises(ConfigError) as refused:
        settings.validate()
    assert str(refused.value) == f"{key}: {message}"


def test_the_decreasing_schedules_bounds_are_taken_at_their_edges():
    DecreasingEpsilonConfig(eps_start=1.0, eps_last=0.0, eps_end=0.0, n_start=0, n_ann=1, n_max=2).validate()


# --- which transitions BMC observes --------------------------------------------------

def test_per_step_counts_one_transition_per_env_step():
    assert [bmc_observation_count(k, 4.0) for k in (1, 2, 3)] == [4, 4, 4]
    assert [bmc_observation_count(k, 2.5) for k in (1, 2, 3, 4)] == [2, 3, 2, 3]  # 10 after 4 updates
    assert sum(bmc_observation_count(k, 0.3) for k in range(1, 11)) == 3


def test_newest_transition_of_each_trace_first():
    g = np.arange(12.0).reshape(4, 3)  # 4 traces of 3 unmasked steps; step 2 is each trace's newest
    greedy, uniform = newest_transitions(g, -g, 4)
    assert greedy.tolist() == [2, 5, 8, 11] and uniform.tolist() == [-2, -5, -8, -11]
    assert newest_transitions(g, g, 6)[0].tolist() == [1, 2, 4, 5, 8, 11]  # then the step before, traces 0 and 1
    assert newest_transitions(g, g, 50)[0].tolist() == list(range(12))  # never more than the batch holds
    assert newest_transitions(g, g, 0)[0].size == 0
    with pytest.raises(ValueError, match="must be equal \\(B, U\\) arrays"):
        newest_transitions(g, g[:2], 3)


@pytest.mark.parametrize("q_values", [[1.0, 2.0], [0.0, math.nan, 0.0, 0.0, 0.0], [[0.0] * 5]])
def test_act_rejects_bad_q_values(q_values):
    with pytest.raises(ValueError, match="q_values"):
        strategy("softmax").act(np.array(q_values), np.random.default_rng(0))


# --- softmax and Max-Boltzmann ----------------------------------------------------------

def test_softmax_probabilities_by_hand():
    # (Q - max Q) / kappa = [0, -1, -2]; e^0 = 1, e^-1 = 0.3678794412, e^-2 = 0.1353352832, sum 1.5032147244
    expected = [1 / 1.5032147244, 0.3678794412 / 1.5032147244, 0.1353352832 / 1.5032147244]
    np.testing.assert_allclose(softmax_probabilities(np.array([0.2, 0.1, 0.0]), 0.1), expected, rtol=1e-9)
    np.testing.assert_allclose(softmax_probabilities(np.array([1.0, 0.0, -1.0]), 1.0), expected, rtol=1e-9)


def test_softmax_of_float32_q_values_is_computed_in_float64():
    q = np.array([0.1, 0.7, 0.3], dtype=np.float32)  # the actor's network gives float32
    exact = np.exp((q.astype(np.float64) - float(q.max())) / 0.1)
    np.testing.assert_allclose(softmax_probabilities(q, 0.1), exact / exact.sum(), rtol=1e-15, atol=0)


def test_the_greedy_action_is_the_largest_q_value_and_a_one_action_strategy_is_allowed():
    policy = strategy("constant")
    policy.config.epsilon = 0.0
    policy.start()
    rng = np.random.default_rng(0)
    assert [policy.act(np.array(q), rng) for q in ([0.0, 0.1, 0.0, 0.9, 0.2], [3.0, 0.0, 0.0, 0.0, 4.0])] == [3, 4]
    assert strategy("constant", n_actions=1).act(np.array([0.5]), rng) == 0
    with pytest.raises(ValueError, match="n_actions must be >= 1, got 0"):
        strategy("constant", n_actions=0)


def test_softmax_does_not_overflow_at_large_q_values():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        # (Q - 1000) / 0.1 = [0, -20000, -1]: e^-20000 underflows to 0, e^-1 = 0.3678794412
        probabilities = softmax_probabilities(np.array([1000.0, -1000.0, 999.9]), 0.1)
    np.testing.assert_allclose(probabilities, [1 / 1.3678794412, 0.0, 0.3678794412 / 1.3678794412], rtol=1e-8)


def test_infinite_temperature_is_uniform():
    np.testing.assert_allclose(softmax_probabilities(np.array([1000.0, -1000.0, 3.0, 0.0]), math.inf), [0.25] * 4)


# Q = [0.2, 0.1, 0.0, 0.15, 0.05] with kappa = 0.1: (Q - 0.2) / 0.1 = [0, -1, -2, -0.5, -1.5];
# e^. = [1, 0.3678794412, 0.1353352832, 0.6065306597, 0.2231301601], sum 2.3328755442.
Q_FIVE = [0.2, 0.1, 0.0, 0.15, 0.05]
SOFTMAX_FIVE = np.array([1, 0.3678794412, 0.1353352832, 0.6065306597, 0.2231301601]) / 2.3328755442


def test_softmax_action_frequencies():
    policy = strategy("softmax")
    policy.start()
    assert (policy.epsilon, policy.kappa) == (1.0, 0.1)
    assert_frequencies(action_counts(policy, Q_FIVE, draws=20_000, seed=2), SOFTMAX_FIVE)


def test_max_boltzmann_action_frequencies():
    policy = MaxBoltzmann(N_ACTIONS, MaxBoltzmannConfig(epsilon=0.3, kappa=0.1))
    policy.start()
    # greedy (action 0) with probability 0.7, else a softmax sample: P = 0.7 * [1, 0, 0, 0, 0] + 0.3 * softmax
    expected = 0.3 * SOFTMAX_FIVE + np.array([0.7, 0, 0, 0, 0])
    np.testing.assert_allclose(expected[0], 0.7 + 0.3 * 0.4286560, atol=1e-6)
    counts = action_counts(policy, Q_FIVE, draws=20_000, seed=3)
    assert_frequencies(counts, expected)
    # and it is not plain epsilon-greedy: uniform exploration would give action 2 0.3 / 5 = 0.06
    assert counts[2] / counts.sum() < 0.03


def test_paper_max_boltzmann_is_mostly_greedy():
    policy = strategy("max_boltzmann")
    policy.start()
    assert (policy.epsilon, policy.kappa) == (0.05, 0.1)
    counts = action_counts(policy, Q_FIVE, draws=20_000, seed=4)
    assert_frequencies(counts, 0.05 * SOFTMAX_FIVE + np.array([0.95, 0, 0, 0, 0]))


def test_constant_epsilon_greedy_frequencies():
    policy = strategy("constant")
    policy.start()
    # greedy 0.95 + 0.05 / 5 = 0.96 on the best action, 0.05 / 5 = 0.01 on each other
    assert_frequencies(action_counts(policy, Q_FIVE, draws=20_000, seed=6), [0.96, 0.01, 0.01, 0.01, 0.01])


# --- decreasing epsilon ---------------------------------------------------------------

# pi_1 = -(1 - 0.1) / 400,000 = -2.25e-6;  pi_0 = 1 + 2.25e-6 * 50,000 = 1.1125
# delta_1 = -(0.1 - 0.01) / (1,000,000 - 400,000 - 50,000) = -0.09 / 550,000
# delta_0 = 0.01 + 0.09 / 550,000 * 1,000,000 = 0.1736363636...
@pytest.mark.parametrize("steps, expected", [
    (0, 1.0),
    (50_000, 1.0),
    (250_000, 1.1125 - 2.25e-6 * 250_000),  # = 1.1125 - 0.5625 = 0.55
    (450_000, 0.1),  # 1.1125 - 1.0125 on the first slope, 0.17364 - 0.07364 on the second
    (725_000, 0.1736363636 - 0.09 * 725_000 / 550_000),  # = 0.17364 - 0.11864 = 0.055
    (1_000_000, 0.01),
])
def test_decreasing_epsilon_at_the_paper_steps(steps, expected):
    assert decreasing_epsilon(steps, DecreasingEpsilonConfig()) == pytest.approx(expected, abs=1e-9)
    policy = DecreasingEpsilonGreedy(N_ACTIONS, DecreasingEpsilonConfig())
    policy.start()
    policy.on_env_steps(steps)
    assert policy.epsilon == pytest.approx(expected, abs=1e-9)


def test_decreasing_epsilon_spot_values_and_hold_after_the_end():
    assert [round(decreasing_epsilon(s, DecreasingEpsilonConfig()), 9) for s in (250_000, 725_000)] == [0.55, 0.055]
    assert decreasing_epsilon(5_000_000, DecreasingEpsilonConfig()) == 0.01


# --- VDBE ----------------------------------------------------------------------------------

def test_vdbe_f_by_hand():
    # Delta = 0.5, nu = 1: e^-0.5 = 0.6065306597; f = 0.3934693403 / 1.6065306597 = 0.2449186624
    assert vdbe_f(0.5, 1.0) == pytest.approx(0.2449186624, abs=1e-9)
    assert vdbe_f(-0.5, 1.0) == pytest.approx(0.2449186624, abs=1e-9)  # |Delta|
    # Delta = 1, nu = 2: e^-0.5 again
    assert vdbe_f(1.0, 2.0) == pytest.approx(0.2449186624, abs=1e-9)
    assert vdbe_f(0.0, 1.0) == 0.0


def test_vdbe_epsilon_update_by_hand():
    policy = strategy("vdbe")
    policy.start()
    assert policy.epsilon == 1.0  # eps_0
    # Deltas: 1.5 - 1.0 = 0.5 and 1.0 - 2.0 = -1.0
    # f(0.5) = 0.2449186624; f(1) = (1 - e^-1) / (1 + e^-1) = 0.6321205588 / 1.3678794412 = 0.4621171573
    # mean f = 0.3535179099; eps = 0.2 * 0.3535179099 + 0.8 * 1 = 0.8707035820
    policy.on_update(np.array([1.0, 2.0]), np.array([1.5, 1.0]))
    assert policy.epsilon == pytest.approx(0.8707035820, abs=1e-9)
    # no change in Q: f = 0, eps = 0.8 * 0.8707035820 = 0.6965628656
    policy.on_update(np.array([3.0]), np.array([3.0]))
    assert policy.epsilon == pytest.approx(0.6965628656, abs=1e-9)
    assert policy.state_dict()["counters"]["updates"] == 2


def test_vdbe_refuses_an_empty_update_by_name():
    policy = strategy("vdbe")
    with pytest.raises(ValueError, match="must be equal-shaped, non-empty and finite"):
        policy.on_update(np.array([]), np.array([]))
    assert policy.epsilon == 1.0 and policy.updates == 0


def test_vdbe_softmax_explores_by_softmax_with_the_vdbe_epsilon():
    policy = strategy("vdbe_softmax")
    policy.start()
    policy.on_update(np.array([1.0, 2.0]), np.array([1.5, 1.0]))
    assert (policy.epsilon, policy.kappa) == (pytest.approx(0.8707035820, abs=1e-9), 0.1)
    expected = 0.8707035820 * SOFTMAX_FIVE + np.array([1 - 0.8707035820, 0, 0, 0, 0])
    assert_frequencies(action_counts(policy, Q_FIVE, draws=20_000, seed=7), expected)


def test_vdbe_rejects_mismatched_arrays():
    with pytest.raises(ValueError, match="q_before"):
        strategy("vdbe").on_update(np.zeros(3), np.zeros(4))


# --- epsilon-BMC ----------------------------------------------------------------------------

def test_greedy_and_uniform_returns_by_hand():
    rewards = np.array([1.0, 0.5])
    next_q = np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]])
    terminated = np.array([False, True])
    g_greedy, g_uniform = greedy_and_uniform_returns(rewards, next_q, terminated, gamma=0.9)
    # first: 1 + 0.9 * max(1, 2, 3) = 3.7 and 1 + 0.9 * mean = 1 + 0.9 * 2 = 2.8; second is terminal: 0.5, 0.5
    np.testing.assert_allclose(g_greedy, [3.7, 0.5])
    np.testing.assert_allclose(g_uniform, [2.8, 0.5])


def test_greedy_and_uniform_returns_of_the_learners_float32_batch_in_float64():
    # Found by mutation testing (deploy/bench/mutation.py). The learner passes (B, U) rewards and
    # terminals and (B, U, A) next Q-values, all float32 (learner/update.py, exploration_terms): the
    # max and mean are over the actions, and the arithmetic is float64, as a float64 reference gets it
    rewards = np.array([[0.1, 0.2], [0.3, 0.4]], dtype=np.float32)
    next_q = np.array([[[0.1, 0.2, 0.7], [1.1, 0.3, 0.3]], [[0.5, 0.6, 0.4], [0.9, 0.8, 0.2]]], dtype=np.float32)
    terminated = np.array([[0.0, 0.0], [0.0, 1.0]], dtype=np.float32)
    g_greedy, g_uniform = greedy_and_uniform_returns(rewards, next_q, terminated, gamma=0.9)
    r, q, t = rewards.astype(np.float64), next_q.astype(np.float64), terminated.astype(np.float64)
    expected_greedy = [[r[i, j] + 0.9 * (1.0 - t[i, j]) * max(q[i, j]) for j in range(2)] for i in range(2)]
    expected_uniform = [[r[i, j] + 0.9 * (1.0 - t[i, j]) * (q[i, j, 0] + q[i, j, 1] + q[i, j, 2]) / 3.0
                         for j in range(2)] for i in range(2)]
    assert g_greedy.dtype == g_uniform.dtype == np.float64
    # float64 rounding of a few operations (~1e-16); float32 anywhere on the way would be ~1e-8 off
    np.testing.assert_allclose(g_greedy, expected_greedy, rtol=1e-14, atol=0)
    np.testing.assert_allclose(g_uniform, expected_uniform, rtol=1e-14, atol=0)
    # terminals that would broadcast but are not one per transition are refused, not spread
    with pytest.raises(ValueError, match="do not describe the same transitions"):
        greedy_and_uniform_returns(rewards, next_q, terminated[:, :1], gamma=0.9)
    with pytest.raises(ValueError, match="do not describe the same transitions"):
        greedy_and_uniform_returns(rewards, next_q[:, :1], terminated, gamma=0.9)


@pytest.mark.parametrize("x, df, loc, scale", [(1.1, 505.0, 0.9, 1.0), (-3.0, 3.0, 0.5, 2.5), (0.0, 1.0, 0.0, 0.1)])
def test_student_t_pdf_matches_scipy(x, df, loc, scale):
    assert student_t_pdf(x, df, loc, scale) == pytest.approx(scipy.stats.t.pdf(x, df, loc=loc, scale=scale), rel=1e-12)


def test_one_bmc_update_step_by_step():
    config = BmcConfig()  # a0 = b0 = 250, mu0 = 0, tau0 = 1
    policy = EpsilonBmc(N_ACTIONS, config)
    policy.start()
    policy.posterior = BmcPosterior(alpha=25.0, beta=25.01, count=4, mean=1.0, m2=0.3)
    policy.on_returns(np.array([1.3]), np.array([0.9]))

    # 2. eps = 25 / 50.01; G = (1 - eps) * 1.3 + eps * 0.9 = 1.3 - 0.4 * eps
    eps = 25.0 / 50.01
    g = 1.3 - 0.4 * eps
    assert eps == pytest.approx(0.4999000200) and g == pytest.approx(1.1000399920)
    # 3. Welford with the fifth return: mean 1.0 + (G - 1) / 5; m2 0.3 + (G - 1) * (G - new mean); var m2 / 4
    mean = 1.0 + (g - 1.0) / 5
    m2 = 0.3 + (g - 1.0) * (g - mean)
    variance = m2 / 4
    # 4. a = 250 + 5/2; b = 250 + 5/2 * var + 5/2 * 1/(1+5) * (mean - 0)^2
    a = 250.0 + 2.5
    b = 250.0 + 2.5 * variance + 2.5 * (1.0 / 6.0) * mean ** 2
    scale = math.sqrt(b / a)
    # 5. evidence of each model under Student-t(df = 2a, loc = G_m, scale)
    e_uniform = scipy.stats.t.pdf(g, 2 * a, loc=0.9, scale=scale)
    e_greedy = scipy.stats.t.pdf(g, 2 * a, loc=1.3, scale=scale)
    # 6. moment matching
    normaliser = e_uniform * 25.0 + e_greedy * 25.01
    m = 25.0 / 51.01 * (e_uniform * 26.0 + e_greedy * 25.01) / normaliser
    s = 25.0 / 51.01 * 26.0 / 52.01 * (e_uniform * 27.0 + e_greedy * 25.01) / normaliser
    r = (m - s) / (s - m * m)

    posterior = policy.posterior
    assert (posterior.count, posterior.mean, posterior.m2) == (5, pytest.approx(mean, rel=1e-12), pytest.approx(m2, rel=1e-12))
    assert posterior.alpha == pytest.approx(m * r, rel=1e-9)
    assert posterior.beta == pytest.approx((1 - m) * r, rel=1e-9)
    assert policy.epsilon == pytest.approx(m, rel=1e-9)
    # With eps < 0.5, G lies nearer G_Q (1.3 - G = 0.19996) than G_U (G - 0.9 = 0.20004): the greedy
    # model gains weight, so epsilon falls, if only a little
    assert policy.epsilon < eps


def test_a_bmc_update_where_every_term_of_the_posterior_counts():
    # Found by mutation testing: with the paper's priors (a0 = b0 = 250) and returns nearly
    # equidistant from both models, the step-by-step test above cannot see the Normal-Gamma b change,
    # a normaliser below 1, or a matched Beta whose alpha + beta is below 1. Small priors, a prior mean
    # off zero, tau0 off 1 and an uneven G make each of them move alpha and beta; the reference is
    # built from the returns themselves (numpy's mean and sample variance, scipy's Student-t), not
    # from the running statistics
    alpha, beta = 0.3, 0.4
    config = BmcConfig(alpha0=alpha, beta0=beta, a0=1.5, b0=0.8, mu0=0.5, tau0=2.0)
    policy = EpsilonBmc(N_ACTIONS, config)
    policy.posterior = BmcPosterior(alpha=alpha, beta=beta, count=3, mean=1.2, m2=0.9)
    earlier = np.array([1.2 - math.sqrt(0.45), 1.2, 1.2 + math.sqrt(0.45)])  # mean 1.2, m2 0.9
    policy.on_returns(np.array([2.0]), np.array([0.7]))

    eps = alpha / (alpha + beta)
    g = (1 - eps) * 2.0 + eps * 0.7
    returns = np.append(earlier, g)
    n, mean, variance = 4, returns.mean(), returns.var(ddof=1)
    a = 1.5 + n / 2
    b = 0.8 + n / 2 * variance + n / 2 * 2.0 / (2.0 + n) * (mean - 0.5) ** 2
    scale = math.sqrt(b / a)
    e_uniform = scipy.stats.t.pdf(g, 2 * a, loc=0.7, scale=scale)
    e_greedy = scipy.stats.t.pdf(g, 2 * a, loc=2.0, scale=scale)
    # the posterior over eps is Beta(alpha, beta) times eps e_U + (1 - eps) e_G: weights alpha e_U and
    # beta e_G on Beta(alpha + 1, beta) and Beta(alpha, beta + 1), matched by its first two moments
    w_u, w_g = alpha * e_uniform, beta * e_greedy
    assert w_u + w_g < 1.0  # a normaliser below 1 is a normaliser like any other
    total = alpha + beta
    first = (w_u * (alpha + 1) + w_g * alpha) / (total + 1) / (w_u + w_g)
    second = (w_u * (alpha + 1) * (alpha + 2) + w_g * alpha * (alpha + 1)) / ((total + 1) * (total + 2)) / (w_u + w_g)
    matched = (first - second) / (second - first ** 2)
    assert matched < 1.0  # alpha + beta of the matched Beta: below 1 is a Beta like any other

    posterior = policy.posterior
    assert posterior.count == 4 and posterior.mean == pytest.approx(mean, rel=1e-12)
    assert posterior.variance == pytest.approx(variance, rel=1e-12)
    assert posterior.alpha == pytest.approx(first * matched, rel=1e-12)
    assert posterior.beta == pytest.approx((1 - first) * matched, rel=1e-12)


def test_returns_of_no_observation_leave_the_posterior_and_bad_returns_are_refused():
    policy = EpsilonBmc(N_ACTIONS, BmcConfig(tau0=1e-6))
    # G 500 from each model in units of a scale near 1: both evidences underflow to 0, and the
    # posterior keeps its Beta rather than divide by zero
    policy.on_returns(np.array([1000.0]), np.array([0.0]))
    assert (policy.posterior.alpha, policy.posterior.beta, policy.posterior.count) == (25.0, 25.01, 1)
    policy.on_returns(np.array([1.0, 2.0, 3.0]), np.array([1.0, 2.0, 3.0]))
    policy.on_returns(np.array([[1.0, 2.0]]), np.array([[0.5, 0.5]]))
    assert policy.returns == 6  # 1 + 3 + 2 transitions, counted over the calls
    for greedy, uniform in (([1.0, 2.0], [1.0]), ([1.0], [math.nan]), ([math.inf], [1.0])):
        with pytest.raises(ValueError, match="must be equal-sized and finite"):
            policy.on_returns(np.array(greedy), np.array(uniform))


def test_the_first_bmc_update_has_zero_variance():
    policy = EpsilonBmc(N_ACTIONS, BmcConfig(alpha0=25.0, beta0=25.0))
    policy.on_returns(np.array([2.0]), np.array([1.0]))
    # eps = 0.5, G = 1.5; count 1, mean 1.5, variance 0 (t <= 1)
    # a = 250.5; b = 250 + 0 + 0.5 * 1/2 * 1.5^2 = 250.5625
    scale = math.sqrt(250.5625 / 250.5)
    # G is as far from G_U as from G_Q, so both evidences are equal: e_U = e_Q = e
    e = scipy.stats.t.pdf(1.5, 501.0, loc=1.0, scale=scale)
    assert e == pytest.approx(scipy.stats.t.pdf(1.5, 501.0, loc=2.0, scale=scale))
    # with equal evidence: m = 25/51 * (26 + 25) / 50 = 0.5; s = 25/51 * 26/52 * (27 + 25) / 50 = 0.2549019608
    # r = (0.5 - 0.2549019608) / (0.2549019608 - 0.25) = 50; alpha = beta = 25: the posterior does not move
    posterior = policy.posterior
    assert (posterior.count, posterior.mean, posterior.variance) == (1, 1.5, 0.0)
    assert posterior.alpha == pytest.approx(25.0, rel=1e-9) and posterior.beta == pytest.approx(25.0, rel=1e-9)
    assert policy.state_dict()["counters"]["returns"] == 1


def test_bmc_epsilon_falls_when_returns_follow_the_greedy_model():
    policy = strategy("bmc")
    policy.start()
    rng = np.random.default_rng(0)
    g_greedy = 1.0 + 0.05 * rng.standard_normal(2_000)
    policy.on_returns(g_greedy, g_greedy - 3.0)
    assert policy.epsilon < 0.05
