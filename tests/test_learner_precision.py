"""learner.precision: the trace passes' convolutions and LSTM input projection in bfloat16, the rest float32.

The bfloat16 update follows the float32 one within bfloat16's rounding, keeps float32 master weights, Adam
state and loss, and learns what float32 learns; "auto" and an explicit bfloat16 degrade or refuse on a CPU
that cannot run bfloat16 (the probe made to report it absent), and the tests that compute in bfloat16 skip,
with the reason, where it is missing.
"""

import dataclasses
import os
import subprocess
import sys

import numpy as np
import pytest
import torch

import common.network as network_module
import learner.update_path as path_module
from common import cpu_capability
from common.config import LearnerConfig
from common.config_values import load_config
from common.schema.fields import ConfigError
from deploy.launcher.stack import StackMonitor
from learner.prefetch import Prefetcher
from learner.metrics import LearnerMetrics
from learner.service import LearnerService
from learner.loss import one_pass_loss
from learner.update import DoubleQLearner
from learner.update_path import candidate_paths, choose_learner_precision, interleaved_cpu_seconds, precision_from_timings
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
    monkeypatch.setattr(path_module, "AUTO_BFLOAT16_SPEEDUP", needed)
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


# --- what is reported is what is computed; auto under load (issue 39) -------------------------------------------

def test_auto_with_the_autograd_path_resolves_to_float32_and_says_so(monkeypatch, caplog):
    """The autograd path computes float32 whatever trace_dtype says: auto must not report bfloat16 there."""
    monkeypatch.setattr(cpu_capability, "bfloat16_native", lambda: True)
    load_config("smoke", overrides={"learner.precision": "auto", "learner.update_path": "autograd"})  # honoured
    automatic = learner("auto", path="autograd")
    with caplog.at_level("INFO", logger="learner.update"):
        automatic.update(random_batch(np.random.default_rng(4)))
    said = [record.getMessage() for record in caplog.records if "learner.precision" in record.getMessage()]
    assert said == ["learner.precision auto: float32, since learner.update_path autograd computes in float32"]
    assert automatic.precision == "float32" and automatic.online.trace_dtype == torch.float32


def test_an_explicit_bfloat16_on_a_float32_only_loss_is_refused(monkeypatch):
    monkeypatch.setattr(cpu_capability, "bfloat16_problem", lambda: None)
    config = dataclasses.replace(LearnerConfig(), precision="bfloat16")
    with pytest.raises(ValueError, match="^learner.precision bfloat16 runs on the trace paths only, not on update "
                                         "path autograd$"):
        DoubleQLearner(TINY, config, loss_function=one_pass_loss)


def test_the_precision_decision_takes_the_best_of_each_candidates_timings():
    # a neighbour's burst in two of float32's three timings and none of bfloat16's must not decide: the best
    # times are 0.30 and 0.20 s, bfloat16 1.5x faster, where the first timings (0.61, 0.55) say 1.1x
    assert precision_from_timings({"float32": [0.61, 0.30, 0.58], "bfloat16": [0.55, 0.20, 0.21]}, 1.3) == "bfloat16"
    assert precision_from_timings({"float32": [0.25], "bfloat16": [0.20]}, 1.3) == "float32"  # 1.25x: not enough
    assert precision_from_timings({"float32": [0.26], "bfloat16": [0.20]}, 1.3) == "bfloat16"  # 1.3x: taken
    # Found by mutation testing: the learner passes no speedup (choose_learner_precision), so the default is
    # what runs, AUTO_BFLOAT16_SPEEDUP = 1.3; and a speedup that is passed is the one used
    assert precision_from_timings({"float32": [0.26], "bfloat16": [0.20]}) == "bfloat16"
    assert precision_from_timings({"float32": [0.25], "bfloat16": [0.20]}) == "float32"
    assert precision_from_timings({"float32": [0.26], "bfloat16": [0.20]}, 1.5) == "float32"


def spinning_neighbours(count: int) -> list[subprocess.Popen]:
    """Processes that keep `count` cores busy until killed: another job sharing the machine."""
    return [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(count)]


def stop(neighbours: list[subprocess.Popen]) -> None:
    for neighbour in neighbours:
        neighbour.kill()
        neighbour.wait(10)


def matrix_work(repeats: int):
    """`repeats` products of two 256 x 256 float32 matrices: a candidate whose cost is known up to its factor."""
    a = torch.randn(256, 256, generator=torch.Generator().manual_seed(0))

    def run() -> None:
        for _ in range(repeats):
            torch.mm(a, a)
    return run


def test_timings_under_a_busy_neighbour_reach_the_quiet_machines_choice():
    """Two candidates whose costs differ by 1.5x, timed while neighbours spin on every core: the decision is
    the one the work itself calls for (bfloat16, at 1.3x or more), and the measured ratio is the quiet one."""
    candidates = {"float32": matrix_work(60), "bfloat16": matrix_work(40)}
    neighbours = spinning_neighbours(os.cpu_count() or 2)
    try:
        seconds = interleaved_cpu_seconds(candidates, rounds=5)
    finally:
        stop(neighbours)
    assert all(len(times) == 5 for times in seconds.values())
    ratio = min(seconds["float32"]) / min(seconds["bfloat16"])
    assert 1.35 < ratio < 1.65, seconds  # 60 / 40 = 1.5: CPU time on one thread does not count the neighbours
    assert precision_from_timings(seconds, 1.3) == "bfloat16"


def test_auto_chooses_under_a_busy_neighbour_as_it_does_quietly_and_the_metrics_name_what_ran(monkeypatch, tmp_path):
    """The whole of learner.precision auto, with neighbours spinning on every core, against the same choice on a
    quiet machine; then the learner's metrics name the precision and path its updates ran. On a CPU without
    bfloat16 convolutions the unfused bfloat16 pass (emulated) is what gets timed."""
    monkeypatch.setattr(cpu_capability, "bfloat16_native", lambda: True)
    if cpu_capability.bfloat16_problem() is not None:
        monkeypatch.setattr(network_module, "fused_relu_convolution_available", lambda device: False)
        monkeypatch.setattr(cpu_capability, "bfloat16_problem", lambda: None)
    batch = random_batch(np.random.default_rng(5))
    quiet, timed, decide = learner("auto"), [], path_module.precision_from_timings
    monkeypatch.setattr(path_module, "precision_from_timings",
                        lambda seconds, speedup=None: timed.append(seconds) or decide(seconds, speedup))
    choose_learner_precision(quiet, quiet.prepare(batch), rounds=5)
    # The tiny network's quiet gain (1.04-1.17x here) lies within noise of the 1.3x the paper's network needs:
    # the bar is set below the quiet gain by a margin, so that bfloat16 is the quiet choice by 25%, and the busy
    # timings must keep it (issue 39's neighbour took 27% of bfloat16's gain).
    quiet_gain = min(timed[0]["float32"]) / min(timed[0]["bfloat16"])
    monkeypatch.setattr(path_module, "AUTO_BFLOAT16_SPEEDUP", 0.75 * quiet_gain)
    quiet_choice = "bfloat16"
    config = load_config("smoke", overrides={
        "network.frame_height": TINY.frame_height, "network.frame_width": TINY.frame_width,
        "network.lstm_units": TINY.lstm_units, "learner.precision": "auto", "learner.update_path": "trace",
        "run.runs_dir": str(tmp_path)})
    service = LearnerService(config)
    neighbours = spinning_neighbours(os.cpu_count() or 2)
    try:
        service.learner.update(random_batch(np.random.default_rng(5), batch=4))
    finally:
        stop(neighbours)
    assert service.learner.precision == quiet_choice
    prefetcher = Prefetcher(lambda request: None, 4, 10, depth=1)
    try:
        stats = LearnerMetrics(service, prefetcher).report()
    finally:
        prefetcher.close()
    assert (stats.precision, stats.update_path) == (quiet_choice, "trace")
    monitor = StackMonitor()
    monitor.on_metric(stats, "d3rqn/r/metrics/learner/0")
    summary = monitor.summary(config)
    assert (summary["learner_precision"], summary["learner_update_path"]) == (quiet_choice, "trace")
