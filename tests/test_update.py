import copy
import threading
import dataclasses
import platform

import numpy as np
import pytest
import torch
from torch import nn

from torch.utils.flop_counter import FlopCounterMode

from common.config import LearnerConfig, NetworkConfig
from common.config_values import load_config
from common.exploration.bmc import greedy_and_uniform_returns
from common.network import D3RQN
from common.schema.fields import ConfigError
from learner.allocator import keep_freed_memory
from deploy.bench.reference_update import paper_reference_loss, same_history_reference_loss
import learner.loss as loss_module
import learner.update_path as path_module
from deploy.bench.flops import update_flops
from learner.loss import (burnt_in_forward, double_q_targets, masked_squared_error, one_pass_loss, one_pass_terms,
                          trace_pass_loss)
from learner.trace_batch import TraceArrays, TraceTensors, to_tensors
from learner.update import DoubleQLearner
from learner.update_path import candidate_paths, choose_update_path

TINY = NetworkConfig(frame_height=36, frame_width=36, lstm_units=16, device="cpu")
LEARNER = LearnerConfig()  # B = 10, T = 10, n_mask = 7, gamma = 0.99, tau = 0.001, lr = 1e-4


@pytest.fixture(autouse=True)
def one_torch_thread():
    """Tiny networks run fastest on one thread, and do not stall when other processes hold the cores."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def random_batch(rng: np.random.Generator, config: NetworkConfig = TINY, batch: int = 10, steps: int = 10,
                 terminal_last: bool = False, stored_state: bool = False) -> TraceArrays:
    frames = (batch, steps + 1, config.frame_height, config.frame_width, config.frame_channels)
    terminated = np.zeros((batch, steps), bool)
    terminated[:, -1] = terminal_last
    states = (rng.random((batch, 2, config.lstm_units)) * 2 - 1).astype(np.float16) if stored_state else None
    return TraceArrays(
        observations=rng.integers(0, 256, frames, dtype=np.uint8),
        actions=rng.integers(0, config.n_actions, (batch, steps)),
        rewards=rng.random((batch, steps)).astype(np.float32),
        terminated=terminated,
        initial_state=states,
    )


def flat_parameters(module: nn.Module) -> torch.Tensor:
    return torch.cat([p.detach().flatten() for p in module.parameters()])


# --- the loss against hand-computed values ----------------------------------------------

class TableQ(nn.Module):
    """Q-values looked up by frame id (the first pixel): no history, so every pass agrees."""

    def __init__(self, table):
        super().__init__()
        self.table = nn.Parameter(torch.tensor(table, dtype=torch.float32))

    def forward(self, frames, state=None):
        return self.table[frames[:, :, 0, 0, 0].long()], (torch.zeros(1), torch.zeros(1))


ONLINE = [[1.0, 2.0], [3.0, 0.0], [0.5, 1.5], [2.0, 4.0]]  # rows: s_0 .. s_3
TARGET = [[0.0, 0.0], [10.0, 20.0], [30.0, 40.0], [50.0, 60.0]]


def table_batch(terminated_last: bool) -> TraceTensors:
    frames = torch.arange(4, dtype=torch.uint8).reshape(1, 4, 1, 1, 1)
    return TraceTensors(observations=frames, actions=torch.tensor([[0, 1, 1]]),
                        rewards=torch.tensor([[1.0, 2.0, 3.0]]),
                        terminated=torch.tensor([[0.0, 0.0, 1.0 if terminated_last else 0.0]]))


@pytest.mark.parametrize("loss_function", [one_pass_loss, paper_reference_loss, same_history_reference_loss])
def test_masked_double_q_loss_by_hand(loss_function):
    online, target = TableQ(ONLINE), TableQ(TARGET)
    # gamma = 0.5, n_mask = 1 of T = 3.
    # t=0 (masked): argmax Q(s1) = 0 -> y = 1 + 0.5 * 10 = 6, Q(s0, a=0) = 1
    # t=1: argmax Q(s2) = [0.5, 1.5] -> 1, y = 2 + 0.5 * 40 = 22, Q(s1, a=1) = 0, error^2 = 484
    # t=2: terminal, y = 3, Q(s2, a=1) = 1.5, error^2 = 2.25
    # loss = (0 + 484 + 2.25) / 3 = 162.083333
    terms = loss_function(online, target, table_batch(terminated_last=True), 0.5, 1)
    assert terms.loss.item() == pytest.approx(486.25 / 3, rel=1e-6)
    # Only the taken actions of unmasked steps get gradient: d/dQ = -2 (y - Q) / 3.
    terms.loss.backward()
    expected = torch.zeros(4, 2)
    expected[1, 1] = -2 * 22 / 3
    expected[2, 1] = -2 * 1.5 / 3
    torch.testing.assert_close(online.table.grad, expected)
    assert target.table.grad is None


def test_a_truncated_last_step_bootstraps():
    online, target = TableQ(ONLINE), TableQ(TARGET)
    # t=2 not terminal: argmax Q(s3) = [2, 4] -> 1, y = 3 + 0.5 * 60 = 33, error^2 = (33 - 1.5)^2 = 992.25
    terms = one_pass_loss(online, target, table_batch(terminated_last=False), 0.5, 1)
    assert terms.loss.item() == pytest.approx((484 + 992.25) / 3, rel=1e-6)


def test_the_loss_from_given_q_values_is_the_papers_one_step_target_unless_told():
    # Found by mutation testing: every caller in the learner passes n_step, so the default went
    # unchecked; deploy/bench/learner_speed.py relies on it. Same table as above, the trace not
    # terminal: t=2 bootstraps from s_3 (y = 33), where two steps would have nothing more to add but
    # t=1 would become 2 + 0.5 * 3 + 0.25 * 60 = 18.5
    online, target = torch.tensor([ONLINE]), torch.tensor([TARGET])
    terms = one_pass_terms(online, target[:, 1:], table_batch(terminated_last=False), 0.5, 1)
    assert terms.loss.item() == pytest.approx((484 + 992.25) / 3, rel=1e-6)


def test_without_burn_in_the_online_pass_starts_from_the_given_state():
    # Found by mutation testing: a stored state with no masked steps (n_mask 0) runs no burn-in, and
    # that pass must still start from the stored (h, c), not from zeros
    torch.manual_seed(0)
    network = D3RQN(TINY)
    frames = torch.from_numpy(np.random.default_rng(0).integers(0, 256, (2, 3, 36, 36, 3), dtype=np.uint8))
    state = (torch.rand(1, 2, TINY.lstm_units) - 0.5, torch.rand(1, 2, TINY.lstm_units) - 0.5)
    with torch.no_grad():
        from_state = burnt_in_forward(network, frames, state, 0)
        torch.testing.assert_close(from_state, network(frames, state)[0], rtol=0, atol=0)
        assert not torch.allclose(from_state, network(frames, None)[0], rtol=0, atol=1e-4)


def test_double_q_targets_and_mask_by_hand():
    next_online = torch.tensor([[[1.0, 5.0], [7.0, 2.0]]])
    next_target = torch.tensor([[[100.0, 10.0], [20.0, 200.0]]])
    # argmax online: 1, 0 -> target 10, 20; y = r + 0.9 * (1 - done) * that
    targets = double_q_targets(torch.tensor([[1.0, 2.0]]), torch.tensor([[0.0, 1.0]]), next_online, next_target, 0.9)
    torch.testing.assert_close(targets, torch.tensor([[10.0, 2.0]]))
    # mean over all 2 * 3 errors, the first n_mask = 2 of each trace weighted 0: (3^2 + 1^2) / 6
    q_taken = torch.tensor([[5.0, 5.0, 0.0], [9.0, 9.0, 2.0]])
    targets = torch.tensor([[0.0, 0.0, 3.0], [0.0, 0.0, 1.0]])
    assert masked_squared_error(q_taken, targets, 2).item() == pytest.approx(10 / 6)


# --- one pass against the separate passes -------------------------------------------------

def losses_and_gradients(loss_function, seed: int, terminal_last: bool = False):
    learner = DoubleQLearner(TINY, LEARNER)
    with torch.no_grad():  # a target unlike the online net, so that mixing them up would show
        for parameter in learner.target.parameters():
            parameter.mul_(1.5)
    tensors = to_tensors(random_batch(np.random.default_rng(seed), terminal_last=terminal_last), TINY, LEARNER,
                         learner.device)
    terms = loss_function(learner.online, learner.target, tensors, LEARNER.gamma, LEARNER.n_mask)
    terms.loss.backward()
    return terms, torch.cat([p.grad.flatten() for p in learner.online.parameters()])


@pytest.mark.parametrize("loss_function, reference_function", [
    (one_pass_loss, same_history_reference_loss),  # one autograd pass against three
    (trace_pass_loss, one_pass_loss),  # the hand-written trace passes against the autograd pass
], ids=["one-pass-vs-separate-passes", "trace-passes-vs-autograd"])
@pytest.mark.parametrize("seed, terminal_last", [(0, False), (1, True)])
def test_one_pass_equals_the_separate_passes_with_the_same_history(loss_function, reference_function, seed,
                                                                   terminal_last):
    one, one_grad = losses_and_gradients(loss_function, seed, terminal_last)
    reference, reference_grad = losses_and_gradients(reference_function, seed, terminal_last)
    assert one.loss.item() == pytest.approx(reference.loss.item(), rel=1e-6)
    torch.testing.assert_close(one.q_values, reference.q_values, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(one.next_q_values, reference.next_q_values, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(one_grad, reference_grad, rtol=1e-4, atol=1e-7)


STORED = dataclasses.replace(LEARNER, stored_state=True, burn_in=2)  # R2D2's stored state, 2 steps of burn-in


def learner_on(path: str, network: NetworkConfig = TINY, config: LearnerConfig = LEARNER) -> DoubleQLearner:
    return DoubleQLearner(network, dataclasses.replace(config, update_path=path))


# The cross-path tolerances. Both paths compute in float32 (unit roundoff u = 2^-24 ~ 6e-8) the same sums in
# different orders, so each quantity differs by rounding alone: a float32 sum of n terms errs by ~sqrt(n) u
# relative to the largest magnitude involved (random signs), n up to 576 here (the LSTM input projection), and the
# 11 LSTM steps and 5 updates pass that on without growing it. Hence every tensor is compared with an absolute
# tolerance scaled by its own largest element, not elementwise relative (elements near zero are sums that cancel,
# whose relative error means nothing), nor a fixed atol (an Adam second moment is ~1e-3 g^2, 1e-9 or less: a fixed
# 1e-9 sits on the rounding itself, which is how an h/c swap once "failed" this test by 1.02e-9).
# Measured worst over seeds 7-9, all three configurations, both paths, scaled by the tensor's largest element:
# loss 2.3e-7, Q-values and BMC returns 4.5e-7, Adam's moments 5.0e-6 (a moment sums 5 gradients, each from
# sums over ~10^3 terms), weight displacements 1.4e-3 (Adam divides by sqrt(v): an element whose gradient is
# rounding noise moves by up to lr either way, so the displacement is the ill-conditioned one).
# A path that reads the stored state as (c, h) moves them by 2e-2, 2.8e-2, 0.16 and 1.6. The tolerances sit
# between, about 20x above the rounding and 100x or more below the swap (the weights: 20x and 50x):
CROSS_PATH_LOSS_RTOL = 1e-5
CROSS_PATH_TERMS_SCALED = 1e-5
CROSS_PATH_MOMENTS_SCALED = 1e-4
CROSS_PATH_MOVES_SCALED = 3e-2


def assert_close_scaled(actual, expected, scaled_atol: float, what: str) -> None:
    """|actual - expected| <= scaled_atol * max|expected|, elementwise."""
    actual, expected = (torch.as_tensor(np.asarray(x) if not isinstance(x, torch.Tensor) else x).double()
                        for x in (actual, expected))
    worst = (actual - expected).abs().max().item()
    bound = scaled_atol * expected.abs().max().item()
    assert worst <= bound, f"{what}: differs by {worst:.3g}, allowed {bound:.3g} ({scaled_atol:g} of its largest)"


@pytest.mark.parametrize("network, config", [
    (TINY, LEARNER), (NetworkConfig(frame_height=44, frame_width=50, lstm_units=24, device="cpu"), LEARNER),
    (TINY, STORED)], ids=["tiny", "cropped-frames", "stored-state"])
@pytest.mark.parametrize("path", ["trace", "trace-split"])
def test_the_update_paths_stay_together_over_several_updates(path, network, config):
    """Five updates from the same weights: the same losses, exploration terms, weights and Adam state as autograd's."""
    rng = np.random.default_rng(7)
    batches = [random_batch(rng, network, terminal_last=bool(k % 2), stored_state=config.stored_state)
               for k in range(5)]
    trace, plain = learner_on(path, network, config), learner_on("autograd", network, config)
    assert (trace.update_path, plain.update_path) == (path, "autograd")
    start = [p.detach().clone() for p in plain.online.parameters()]
    for k, batch in enumerate(batches):
        with_q_after = k >= 3
        torch.set_num_threads(2 if path == "trace-split" else 1)  # split: one for each pass
        a = trace.update(batch, with_q_after=with_q_after)
        torch.set_num_threads(1)
        b = plain.update(batch, with_q_after=with_q_after)
        assert a.update == b.update == k + 1
        assert a.loss == pytest.approx(b.loss, rel=CROSS_PATH_LOSS_RTOL)
        for name in ("q_before", "g_greedy", "g_uniform") + (("q_after",) if with_q_after else ()):
            assert_close_scaled(getattr(a, name), getattr(b, name), CROSS_PATH_TERMS_SCALED, f"update {k} {name}")
    for (name, moved), kept, first in zip(trace.online.named_parameters(), plain.online.parameters(), start):
        assert_close_scaled(moved.detach() - first, kept.detach() - first, CROSS_PATH_MOVES_SCALED, f"{name} moved")
    for network_name in ("online", "target"):
        for (name, a_p), b_p in zip(getattr(trace, network_name).named_parameters(),
                                    getattr(plain, network_name).parameters()):
            torch.testing.assert_close(a_p, b_p, rtol=1e-4, atol=1e-6, msg=f"{network_name} {name}")
    for (a_state, b_state), name in zip(zip(trace.optimizer.state.values(), plain.optimizer.state.values()),
                                        (name for name, _ in plain.online.named_parameters())):
        for key in ("exp_avg", "exp_avg_sq"):
            assert_close_scaled(a_state[key], b_state[key], CROSS_PATH_MOMENTS_SCALED, f"{name} {key}")
    assert not torch.equal(flat_parameters(trace.online), flat_parameters(learner_on(path, network, config).online))


def test_auto_times_every_path_once_per_process_and_changes_nothing(monkeypatch):
    monkeypatch.setattr(path_module, "_chosen_paths", {})
    timed = []
    original = DoubleQLearner._update
    monkeypatch.setattr(DoubleQLearner, "_update",
                        lambda self, *args, **kwargs: timed.append(self.update_path) or original(self, *args, **kwargs))
    torch.set_num_threads(2)  # "trace-split" needs two
    first = learner_on("auto")
    assert first.update_path == "auto"
    before = flat_parameters(first.online), flat_parameters(first.target)
    tensors = first.prepare(random_batch(np.random.default_rng(8)))
    chosen = choose_update_path(first, tensors, rounds=2)
    assert chosen in ("trace", "trace-split", "autograd")
    assert sorted(set(timed)) == ["autograd", "trace", "trace-split"] and len(timed) == 9  # 1 untimed + 2 each
    assert torch.equal(flat_parameters(first.online), before[0]) and torch.equal(flat_parameters(first.target), before[1])
    assert first.updates == 0 and not first.optimizer.state and first.update_path == "auto"
    second = learner_on("auto")
    second.update(random_batch(np.random.default_rng(9)))  # the same sizes and threads: no second measurement
    assert len(timed) == 10 and second.update_path == chosen and second.updates == 1
    assert candidate_paths(torch.device("cpu"), 1) == ["trace", "autograd"]
    assert candidate_paths(torch.device("cuda"), 4) == ["trace", "autograd"]


def test_an_unknown_update_path_is_a_config_error():
    with pytest.raises(ConfigError, match="learner.update_path"):
        load_config("paper", overrides={"learner.update_path": "fast"})


def test_the_flop_count_matches_torchs_counter_on_the_autograd_path():
    """deploy/bench/flops.py against torch.utils.flop_counter on one loss and backward pass of today's code."""
    learner = learner_on("autograd")
    tensors = learner.prepare(random_batch(np.random.default_rng(10)))
    with FlopCounterMode(display=False) as counter:
        one_pass_loss(learner.online, learner.target, tensors, LEARNER.gamma, LEARNER.n_mask).loss.backward()
    assert counter.get_total_flops() == sum(update_flops(TINY, LEARNER, backward_steps=11).values())


def test_one_update_at_the_papers_sizes_is_19_4_gflop():
    phases = update_flops(NetworkConfig(), LearnerConfig())
    assert sum(phases.values()) == pytest.approx(19.399e9, rel=1e-4)
    assert phases["target forward"] == pytest.approx(phases["online forward: conv"] + phases["online forward: lstm + head"])


def test_the_paper_passes_see_one_frame_less_history():
    one, _ = losses_and_gradients(one_pass_loss, seed=0)
    paper, _ = losses_and_gradients(paper_reference_loss, seed=0)
    # Q(h_t, .) comes from the same pass over s_0..s_T-1 in both...
    torch.testing.assert_close(one.q_values, paper.q_values)
    # ...but the paper's next-state pass restarts at s_1 from a zero state, so h_t+1 lacks s_0.
    gap = (one.next_q_values - paper.next_q_values).abs().max().item()
    relative = abs(one.loss.item() - paper.loss.item()) / one.loss.item()
    print(f"paper-style reference: max |dQ(h_t+1)| {gap:.2e}, relative loss difference {relative:.2e}")
    assert gap > 1e-5 and relative > 1e-6


# --- the learner step ----------------------------------------------------------------------

def test_the_target_starts_as_a_copy_of_the_online_network():
    learner = DoubleQLearner(TINY, LEARNER)
    for (name, online), target in zip(learner.online.named_parameters(), learner.target.parameters()):
        assert torch.equal(online, target), name
        assert online.data_ptr() != target.data_ptr()
        assert not target.requires_grad


def test_soft_update_arithmetic():
    learner = DoubleQLearner(TINY, LEARNER)
    with torch.no_grad():
        for online, target in zip(learner.online.parameters(), learner.target.parameters()):
            online.fill_(1.0)
            target.fill_(0.0)
    learner.soft_update_target()
    # 0.001 * 1 + 0.999 * 0 = 0.001
    torch.testing.assert_close(flat_parameters(learner.target), torch.full_like(flat_parameters(learner.target), 0.001))
    learner.soft_update_target()
    # 0.001 * 1 + 0.999 * 0.001 = 0.001999
    torch.testing.assert_close(flat_parameters(learner.target), torch.full_like(flat_parameters(learner.target), 0.001999))


def test_the_soft_update_comes_before_the_gradient_step():
    learner = DoubleQLearner(TINY, LEARNER)
    with torch.no_grad():
        for target in learner.target.parameters():
            target.mul_(-1.0)
    online_before, target_before = flat_parameters(learner.online), flat_parameters(learner.target)
    learner.update(random_batch(np.random.default_rng(0)))
    torch.testing.assert_close(flat_parameters(learner.target), 0.001 * online_before + 0.999 * target_before)
    assert not torch.equal(flat_parameters(learner.online), online_before)
    assert learner.updates == 1


def test_update_returns_what_the_strategies_need():
    learner = DoubleQLearner(TINY, LEARNER)
    batch = random_batch(np.random.default_rng(2), terminal_last=True)
    frames = torch.from_numpy(batch.observations)
    with torch.no_grad():
        q_before = learner.online(frames)[0]  # over s_0..s_T with the weights before the step
    result = learner.update(batch, with_q_after=True)
    with torch.no_grad():
        q_after = learner.online(frames)[0]

    greedy = q_before[:, 7:10].argmax(dim=-1, keepdim=True)  # a*_t of the 3 unmasked steps t = 7, 8, 9
    assert result.q_before.shape == result.q_after.shape == result.g_greedy.shape == result.g_uniform.shape == (10, 3)
    np.testing.assert_allclose(result.q_before, q_before[:, 7:10].max(dim=-1).values.numpy(), rtol=1e-5)
    np.testing.assert_allclose(result.q_after, q_after[:, 7:10].gather(-1, greedy).squeeze(-1).numpy(), rtol=1e-5)
    assert not np.allclose(result.q_after, result.q_before)
    g_greedy, g_uniform = greedy_and_uniform_returns(
        batch.rewards[:, 7:], q_before[:, 8:11].numpy(), batch.terminated[:, 7:], LEARNER.gamma)
    np.testing.assert_allclose(result.g_greedy, g_greedy, rtol=1e-5)
    np.testing.assert_allclose(result.g_uniform, g_uniform, rtol=1e-5)
    # the last step is terminal: G_Q = G_U = r
    np.testing.assert_allclose(result.g_greedy[:, -1], batch.rewards[:, -1], rtol=1e-6)
    np.testing.assert_allclose(result.g_uniform[:, -1], batch.rewards[:, -1], rtol=1e-6)
    assert result.update == 1 and result.loss > 0


def test_q_after_is_computed_only_when_asked():
    learner = DoubleQLearner(TINY, LEARNER)
    assert learner.update(random_batch(np.random.default_rng(3))).q_after is None


def test_checkpoint_round_trip_continues_identically():
    rng = np.random.default_rng(4)
    batches = [random_batch(rng) for _ in range(3)]
    first = DoubleQLearner(TINY, LEARNER)
    for batch in batches[:2]:
        first.update(batch)
    second = DoubleQLearner(TINY, dataclasses.replace(LEARNER, seed=9))
    second.load_state_dict(copy.deepcopy(first.state_dict()))
    assert second.updates == 2
    assert first.update(batches[2]).loss == second.update(batches[2]).loss
    assert torch.equal(flat_parameters(first.online), flat_parameters(second.online))
    assert torch.equal(flat_parameters(first.target), flat_parameters(second.target))


def test_a_checkpoint_of_another_network_is_a_value_error():
    other = DoubleQLearner(dataclasses.replace(TINY, lstm_units=8), LEARNER)
    learner = DoubleQLearner(TINY, LEARNER)
    with pytest.raises(ValueError, match="does not fit"):
        learner.load_state_dict(other.state_dict())
    with pytest.raises(ValueError, match="lacks"):
        learner.load_state_dict({"online": {}})


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="mallopt is glibc's")
def test_the_allocator_setting_takes_effect_on_glibc():
    assert keep_freed_memory()


def test_the_learner_seed_fixes_the_initial_weights_without_touching_the_global_rng():
    state = torch.random.get_rng_state()
    a, b = DoubleQLearner(TINY, LEARNER), DoubleQLearner(TINY, LEARNER)
    assert torch.equal(torch.random.get_rng_state(), state)
    assert torch.equal(flat_parameters(a.online), flat_parameters(b.online))
    c = DoubleQLearner(TINY, dataclasses.replace(LEARNER, seed=1))
    assert not torch.equal(flat_parameters(a.online), flat_parameters(c.online))


def bad_batches():
    good = random_batch(np.random.default_rng(5))
    yield dataclasses.replace(good, observations=good.observations.astype(np.float32)), "observations must be uint8"
    yield dataclasses.replace(good, observations=good.observations[:, :10]), "observations must be uint8"
    yield dataclasses.replace(good, actions=good.actions[:, :9]), "actions must have shape"
    yield dataclasses.replace(good, actions=good.actions + 5), r"actions must be integers in \[0, 5\)"
    yield dataclasses.replace(good, actions=good.actions.astype(float)), "actions must be integers"
    yield dataclasses.replace(good, rewards=np.full((10, 10), np.nan)), "rewards must be finite"
    yield dataclasses.replace(good, terminated=np.full((10, 10), 2)), "terminated must hold only"


@pytest.mark.parametrize("batch, message", list(bad_batches()))
def test_a_malformed_batch_is_a_value_error(batch, message):
    learner = DoubleQLearner(TINY, LEARNER)
    with pytest.raises(ValueError, match=message):
        learner.update(batch)
    assert learner.updates == 0


# --- done when: it learns -----------------------------------------------------------------

def paying_action_margin(learner: DoubleQLearner, updates: int = 200, best: int = 3) -> torch.Tensor:
    """Random images, reward 1 for action `best` and 0 otherwise: after the updates, Q of `best` minus the
    highest other Q, at every unmasked step of a fresh batch."""
    rng = np.random.default_rng(6)

    def batch():
        random = random_batch(rng)
        return dataclasses.replace(random, rewards=(random.actions == best).astype(np.float32))

    for _ in range(updates):
        learner.update(batch())
    with torch.no_grad():
        q_values = learner.online(torch.from_numpy(batch().observations))[0][:, learner.config.n_mask:]
    others = torch.cat([q_values[..., :best], q_values[..., best + 1:]], dim=-1)
    return q_values[..., best] - others.max(dim=-1).values


def test_learns_which_action_pays_on_a_synthetic_task():
    """After 200 paper-setting updates (lr 1e-4, gamma 0.99, tau 0.001, n_mask 7 of 10) the paying action
    has the highest Q everywhere."""
    margin = paying_action_margin(DoubleQLearner(TINY, LEARNER))
    assert margin.min() > 0.5, margin  # reward 1 for the best action, 0 for the others


# --- batches staged ahead of their update (learner.trace_batch.BatchStager, learner.prefetch) ----

def test_a_staged_batch_updates_exactly_like_a_plain_one():
    batch = random_batch(np.random.default_rng(11), terminal_last=True)
    plain, staged = learner_on("trace"), learner_on("trace")
    tensors = staged.stager().stage(batch)
    assert tensors.pixels is not None and tensors.ready is None  # CPU: frames scaled ahead, nothing to wait for
    a, b = plain.update(batch, with_q_after=True), staged.update(tensors, with_q_after=True)
    assert a.loss == b.loss
    np.testing.assert_array_equal(a.q_after, b.q_after)
    assert torch.equal(flat_parameters(plain.online), flat_parameters(staged.online))


def test_staging_checks_the_batch_like_update():
    good = random_batch(np.random.default_rng(12))
    with pytest.raises(ValueError, match="rewards must be finite"):
        learner_on("trace").stager().stage(dataclasses.replace(good, rewards=np.full((10, 10), np.nan)))


def test_the_prefetcher_prepares_batches_in_its_workers_and_hands_on_their_errors():
    from learner.prefetch import Prefetcher
    batches = iter([random_batch(np.random.default_rng(13)), None, "bad"])
    learner = learner_on("trace")
    threads = []

    def fetch(request):
        return next(batches, None)

    def prepare(batch):
        threads.append(threading.current_thread().name)
        if batch == "bad":
            raise ValueError("a bad batch")
        return learner.stager().stage(batch)

    prefetcher = Prefetcher(fetch, batch_size=10, trace_length=10, depth=1, prepare=prepare)
    stop = threading.Event()
    try:
        staged = prefetcher.next(stop, timeout_s=10)
        assert isinstance(staged, TraceTensors) and staged.pixels is not None
        with pytest.raises(ValueError, match="a bad batch"):
            prefetcher.next(stop, timeout_s=10)
    finally:
        prefetcher.close()
    assert threads == ["prefetch-0", "prefetch-0"]
    assert learner.update(staged).update == 1


@pytest.mark.skipif(not torch.cuda.is_available(),
                    reason="CUDA only: pinned host buffers and copies on a side stream need a CUDA device")
def test_staged_copies_to_cuda_update_like_the_cpu():
    network = dataclasses.replace(TINY, device="cuda")
    rng = np.random.default_rng(14)
    batches = [random_batch(rng) for _ in range(3)]
    cuda, cpu = DoubleQLearner(network, LEARNER), learner_on("autograd")
    stager = cuda.stager()
    staged = [stager.stage(batch) for batch in batches]  # three batches through two pinned slots
    assert all(t.ready is not None and t.observations.device.type == "cuda" for t in staged)
    with torch.backends.cudnn.flags(enabled=True, allow_tf32=False):  # TF32 convolutions round to 10 bits
        for batch, tensors in zip(batches, staged):
            a, b = cuda.update(tensors), cpu.update(batch)
            assert a.loss == pytest.approx(b.loss, rel=1e-3)
    torch.testing.assert_close(flat_parameters(cuda.online).cpu(), flat_parameters(cpu.online), rtol=1e-3, atol=1e-5)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA only: the update paths on a CUDA device")
def test_auto_on_cuda_times_trace_and_autograd_only():
    learner = DoubleQLearner(dataclasses.replace(TINY, device="cuda"), dataclasses.replace(LEARNER, update_path="auto"))
    learner.update(random_batch(np.random.default_rng(15)))
    assert learner.update_path in ("trace", "autograd")
    assert all(len({weight.untyped_storage().data_ptr() for weight in network.lstm.parameters()}) == 1
               for network in (learner.online, learner.target))  # cuDNN's one packed buffer, in the target too


def test_a_cuda_device_is_a_config_choice_the_learner_follows():
    """The device switch on a CPU-only machine: "cpu" and "auto" put the learner on the CPU."""
    for device in ("cpu", "auto"):
        learner = DoubleQLearner(dataclasses.replace(TINY, device=device), LEARNER)
        expected = "cuda" if device == "auto" and torch.cuda.is_available() else "cpu"
        assert learner.device.type == expected == learner.prepare(random_batch(np.random.default_rng(16))).observations.device.type


# --- n-step targets (learner.n_step, beyond the paper) ------------------------------------------------------

R = torch.tensor([[1.0, 2.0, 3.0, 4.0]])
NEXT_ONLINE = torch.tensor([[[0.0, 1.0], [1.0, 0.0], [0.0, 1.0], [1.0, 0.0]]])  # greedy in s1..s4: 1, 0, 1, 0
NEXT_TARGET = torch.tensor([[[10.0, 20.0], [30.0, 40.0], [50.0, 60.0], [70.0, 80.0]]])  # so s1..s4 bootstrap 20, 30, 60, 70


@pytest.mark.parametrize("n_step, expected", [
    # gamma 0.5, s3 terminal (terminated[2]):
    (1, [1 + 0.5 * 20, 2 + 0.5 * 30, 3, 4 + 0.5 * 70]),
    # t=0: 1 + 0.5 * 2 + 0.25 * 30; t=1: 2 + 0.5 * 3, the terminal stops the bootstrap; t=3: the trace ends
    (2, [1 + 1 + 0.25 * 30, 2 + 1.5, 3, 4 + 0.5 * 70]),
    (3, [1 + 1 + 0.75, 2 + 1.5, 3, 4 + 0.5 * 70]),  # t=0: the terminal at s3 ends the sum after r_2
])
def test_n_step_targets_by_hand(n_step, expected):
    terminated = torch.tensor([[0.0, 0.0, 1.0, 0.0]])
    targets = double_q_targets(R, terminated, NEXT_ONLINE, NEXT_TARGET, 0.5, n_step)
    torch.testing.assert_close(targets, torch.tensor([expected]))


def test_n_step_targets_without_a_terminal_bootstrap_from_the_window_or_the_traces_end():
    targets = double_q_targets(R, torch.zeros(1, 4), NEXT_ONLINE, NEXT_TARGET, 0.5, 2)
    # t=2: 3 + 0.5 * 4 + 0.25 * 70 (s4: the trace's last state); t=3: only one step is left
    torch.testing.assert_close(targets, torch.tensor([[1 + 1 + 0.25 * 30, 2 + 1.5 + 0.25 * 60,
                                                       3 + 2 + 0.25 * 70, 4 + 0.5 * 70]]))


@pytest.mark.parametrize("path", ["trace", "autograd"])
def test_the_learner_uses_n_step_targets_on_every_path(path):
    rng = np.random.default_rng(11)
    batch = random_batch(rng, terminal_last=True)
    results = {}
    for n_step in (1, 3):
        learner = DoubleQLearner(TINY, dataclasses.replace(LEARNER, update_path=path, n_step=n_step))
        tensors = learner.prepare(batch)
        expected = one_pass_loss(learner.online, learner.target, tensors, LEARNER.gamma, LEARNER.n_mask, n_step)
        results[n_step] = learner.update(batch).loss
        # the update's soft target step moves the target by tau only: the loss it reports is the one computed
        assert results[n_step] == pytest.approx(expected.loss.item(), rel=1e-3)
    assert results[1] != pytest.approx(results[3], rel=1e-3)


def test_n_step_is_a_config_choice_within_the_trace():
    assert load_config("paper").learner.n_step == 1
    with pytest.raises(ConfigError, match="learner.n_step"):
        load_config("paper", overrides={"learner.n_step": 0})
    with pytest.raises(ConfigError, match="learner.n_step"):
        load_config("paper", overrides={"learner.n_step": 11})


# --- stored recurrent state and burn-in (learner.stored_state, beyond the paper) ----------------------

def test_the_masked_steps_are_n_mask_from_the_zero_state_and_burn_in_from_a_stored_one():
    assert LEARNER.masked_steps == 7 and STORED.masked_steps == 2
    with pytest.raises(ConfigError, match="burn_in"):
        dataclasses.replace(LEARNER, burn_in=2).validate()  # burn-in without a stored state
    with pytest.raises(ConfigError, match="burn_in"):
        dataclasses.replace(STORED, burn_in=10).validate()
    dataclasses.replace(STORED, burn_in=0).validate()  # the stored state alone: every error counts


def test_a_stored_state_reaches_the_loss_and_a_learner_that_uses_it_refuses_a_batch_without_it():
    rng = np.random.default_rng(31)
    batch = random_batch(rng, stored_state=True)
    learner = DoubleQLearner(TINY, STORED)
    with_state = one_pass_loss(learner.online, learner.target, learner.prepare(batch), 0.99, 2).loss.item()
    zero_state = one_pass_loss(learner.online, learner.target,
                               learner.prepare(dataclasses.replace(batch, initial_state=np.zeros_like(batch.initial_state))),
                               0.99, 2).loss.item()
    assert with_state != pytest.approx(zero_state, rel=1e-4)
    with pytest.raises(ValueError, match="initial_state"):
        learner.prepare(dataclasses.replace(batch, initial_state=None))
    with pytest.raises(ValueError, match="initial_state"):
        learner.prepare(dataclasses.replace(batch, initial_state=batch.initial_state[:, :, :3]))
    paper = DoubleQLearner(TINY, LEARNER)  # the paper's learner ignores a stored state: every trace from zero
    assert paper.prepare(batch).initial_state is None


def test_burn_in_steps_of_a_stored_state_batch_carry_no_gradient():
    """The autograd path's burn-in: Q-values of the first burn_in steps have no graph, the later ones do,
    and they equal one forward pass from the stored state (no gradient changes values)."""
    learner = DoubleQLearner(TINY, STORED)
    tensors = learner.prepare(random_batch(np.random.default_rng(32), stored_state=True))
    state = loss_module.start_state(tensors)
    q_values = loss_module.burnt_in_forward(learner.online, tensors.observations, state, 2)
    assert loss_module.burn_in_steps(tensors, 2) == 2 and q_values.requires_grad
    q_values[:, :2].sum().backward(retain_graph=True)
    assert all(p.grad is None or not p.grad.any() for p in learner.online.parameters())
    with torch.no_grad():
        whole, _ = learner.online(tensors.observations, state)
    torch.testing.assert_close(q_values.detach(), whole, rtol=1e-5, atol=1e-6)
    weights = torch.randn(q_values[:, 2:].shape, generator=torch.Generator().manual_seed(33))  # not a plain sum:
    (q_values[:, 2:] * weights).sum().backward()  # the advantages' mean is subtracted, a sum over actions is 0
    assert all(p.grad is not None and p.grad.abs().max() > 0 for p in learner.online.parameters())


def test_a_read_only_stored_state_moves_to_float32_without_a_warning(recwarn):
    batch = random_batch(np.random.default_rng(3), stored_state=True)
    batch.initial_state.flags.writeable = False  # as the wire's bytes arrive
    tensors = to_tensors(batch, TINY, LearnerConfig(stored_state=True), torch.device("cpu"))
    assert tensors.initial_state.dtype == torch.float32
    assert torch.equal(tensors.initial_state, torch.from_numpy(batch.initial_state.astype(np.float32)))
    assert not [w for w in recwarn if "not writable" in str(w.message)]
