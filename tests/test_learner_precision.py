"""learner.precision: the trace passes' convolutions and LSTM input projection in bfloat16, the rest float32.

The bfloat16 update follows the float32 one within bfloat16's rounding, keeps float32 master weights, Adam
state and loss, and learns what float32 learns; "auto" and an explicit bfloat16 degrade or refuse on a CPU
that cannot run bfloat16 (the probe made to report it absent), and the tests that compute in bfloat16 skip,
with the reason, where it is missing.
"""

import dataclasses

import numpy as np
import pytest
import torch

import learner.update as update_module
from common import cpu_capability
from common.config import LearnerConfig
from common.config_values import load_config
from common.options import ConfigError
from learner.update import DoubleQLearner, candidate_paths, choose_learner_precision
from tests.cpu_support import needs_bfloat16
from tests.test_update import (TINY, flat_parameters, one_torch_thread,  # noqa: F401 (an autouse fixture)
                               paying_action_margin, random_batch)

ABSENT = "this CPU (a test's) lacks the avx512bw+avx512vl+avx512dq or avx_ne_convert instructions"


def learner(precision: str, path: str = "trace", **overrides) -> DoubleQLearner:
    return DoubleQLearner(TINY, dataclasses.replace(LearnerConfig(), precision=precision, update_path=path,
                                                    **overrides))


@needs_bfloat16
def test_a_bfloat16_update_follows_float32_within_rounding_and_keeps_float32_state():
    rng = np.random.default_rng(3)
    batches = [random_batch(rng, terminal_last=bool(k % 2)) for k in range(4)]
    exact, compact = learner("float32"), learner("bfloat16")
    for batch in batches:
        a, b = exact.update(batch, with_q_after=True), compact.update(batch, with_q_after=True)
        assert b.loss == pytest.approx(a.loss, rel=0.05)  # bfloat16 keeps 8 bits of mantissa
        np.testing.assert_allclose(b.q_before, a.q_before, rtol=0.05, atol=0.02)
        np.testing.assert_allclose(b.q_after, a.q_after, rtol=0.05, atol=0.02)
    assert all(parameter.dtype == torch.float32 for parameter in compact.online.parameters())
    assert all(moment.dtype == torch.float32 for state in compact.optimizer.state.values()
               for moment in (state["exp_avg"], state["exp_avg_sq"]))
    assert all(parameter.grad.dtype == torch.float32 for parameter in compact.online.parameters())
    moved = flat_parameters(compact.online) - flat_parameters(learner("bfloat16").online)
    expected = flat_parameters(exact.online) - flat_parameters(learner("float32").online)
    assert torch.nn.functional.cosine_similarity(moved, expected, dim=0) > 0.95  # the same steps, rounded


@needs_bfloat16
def test_bfloat16_learns_which_action_pays_as_float32_does():
    margin = paying_action_margin(learner("bfloat16"))
    assert margin.min() > 0.5, margin


def test_float32_leaves_the_trace_pass_as_it_was():
    exact = learner("float32")
    assert exact.online.trace_dtype == exact.target.trace_dtype == torch.float32


def test_auto_takes_float32_with_one_log_line_where_the_cpu_has_no_native_bfloat16(monkeypatch, caplog):
    monkeypatch.setattr(cpu_capability, "bfloat16_native", lambda: False)
    monkeypatch.setattr(cpu_capability, "bfloat16_problem", lambda: ABSENT)
    automatic = learner("auto")
    with caplog.at_level("INFO", logger="learner.update"):
        automatic.update(random_batch(np.random.default_rng(1)))
    said = [record.getMessage() for record in caplog.records if "learner.precision" in record.getMessage()]
    assert said == [f"learner.precision auto: float32, since {ABSENT}"]
    assert automatic.precision == "float32" and automatic.online.trace_dtype == torch.float32


@needs_bfloat16
@pytest.mark.parametrize("needed, chosen", [(0.0, "bfloat16"), (1e9, "float32")])
def test_auto_takes_bfloat16_only_when_it_times_fast_enough_and_changes_nothing(monkeypatch, needed, chosen):
    monkeypatch.setattr(cpu_capability, "bfloat16_native", lambda: True)
    monkeypatch.setattr(update_module, "AUTO_BFLOAT16_SPEEDUP", needed)
    automatic = learner("auto")
    before = flat_parameters(automatic.online)
    tensors = automatic.prepare(random_batch(np.random.default_rng(2)))
    assert choose_learner_precision(automatic, tensors, rounds=1) == chosen
    assert torch.equal(flat_parameters(automatic.online), before) and automatic.updates == 0


def test_an_explicit_bfloat16_is_refused_where_it_cannot_run(monkeypatch):
    monkeypatch.setattr(cpu_capability, "bfloat16_problem", lambda: ABSENT)
    with pytest.raises(cpu_capability.PrecisionUnavailable, match="^learner.precision = bfloat16 cannot run here"):
        learner("bfloat16")


def test_bfloat16_runs_on_the_trace_paths_only():
    with pytest.raises(ConfigError, match="learner.precision"):
        load_config("smoke", overrides={"learner.precision": "bfloat16", "learner.update_path": "autograd"})
    with pytest.raises(ConfigError, match="learner.precision"):
        load_config("smoke", overrides={"learner.precision": "half"})
    assert candidate_paths(torch.device("cpu"), 2, "bfloat16") == ["trace", "trace-split"]
    assert load_config("paper").learner.precision == "float32"
