"""What the learner times at its start: the update path (learner.update_path auto: the trace passes, with
or without a helper thread, or autograd) and the number format (learner.precision auto: bfloat16 only
where it is clearly faster). Each choice is measured on the first batch and said in one log line.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from typing import TYPE_CHECKING, Callable

import torch

from common import cpu_capability
from learner.loss import LossFunction, one_pass_loss, trace_pass_loss
from learner.trace_batch import TraceTensors

if TYPE_CHECKING:
    from learner.update import DoubleQLearner

log = logging.getLogger("learner.update")


UPDATE_PATHS: dict[str, tuple[LossFunction, bool]] = {
    "trace": (trace_pass_loss, False),
    "trace-split": (trace_pass_loss, True),
    "autograd": (one_pass_loss, False),
}

_chosen_paths: dict[tuple, str] = {}  # choose_update_path's measurements, per process
AUTO_BFLOAT16_SPEEDUP = 1.3  # learner.precision auto: a smaller gain is not worth other numbers than the paper's

def candidate_paths(device: torch.device, threads: int, precision: str = "float32") -> list[str]:
    """The update paths worth timing: "trace-split" needs two torch threads; on CUDA one stream does it all;
    bfloat16 runs on the trace paths only."""
    return [name for name in UPDATE_PATHS if (name != "trace-split" or (device.type == "cpu" and threads >= 2))
            and (name != "autograd" or precision == "float32")]


def choose_learner_precision(learner: DoubleQLearner, batch: TraceTensors, rounds: int = 5) -> str:
    """learner.precision auto: bfloat16 where the CPU does it natively and whole updates of the trace path
    time at least AUTO_BFLOAT16_SPEEDUP faster than in float32; float32 otherwise. One log line says why.

    The timings are made to hold when another process shares the CPU (issue 39: a busy neighbour once made
    bfloat16's 1.5x look like 1.1x): interleaved_cpu_seconds counts the CPU time of one torch thread, which a
    neighbour's time slices do not inflate, over several interleaved rounds, and the best of each is compared."""
    if learner.update_path in ("autograd", "custom"):
        log.info("learner.precision auto: float32, since learner.update_path %s computes in float32",
                 learner.update_path)
        return "float32"
    if learner.device.type != "cpu" or not cpu_capability.bfloat16_native():
        why = ("the learner is on " + learner.device.type if learner.device.type != "cpu" else
               cpu_capability.bfloat16_problem() or "this CPU has no native bfloat16 (AMX or AVX512-BF16)")
        log.info("learner.precision auto: float32, since %s", why)
        return "float32"
    scratch = learner.scratch_copy()
    scratch.use_path("trace")

    def update_in(precision: str) -> Callable[[], None]:
        def run() -> None:
            scratch.use_precision(precision)
            scratch._update(batch, with_q_after=False)
        return run

    seconds = interleaved_cpu_seconds({precision: update_in(precision) for precision in ("float32", "bfloat16")},
                                      rounds)
    del scratch
    chosen = precision_from_timings(seconds)
    best = {precision: min(times) for precision, times in seconds.items()}
    log.info("learner.precision auto: %s (best of %d interleaved updates each, CPU time on one thread: float32 "
             "%.1f ms, bfloat16 %.1f ms; bfloat16 is taken at %.1fx or more)", chosen, rounds,
             1e3 * best["float32"], 1e3 * best["bfloat16"], AUTO_BFLOAT16_SPEEDUP)
    return chosen


def precision_from_timings(seconds: dict[str, list[float]], speedup: float | None = None) -> str:
    """bfloat16 when its best time is at least `speedup` (AUTO_BFLOAT16_SPEEDUP) times shorter than float32's.

    The best (minimum) of the repeats: noise from other processes only ever adds time, so the minimum is the
    closest to what a quiet machine measures, where a mean or a single timing carries the neighbour's share."""
    speedup = AUTO_BFLOAT16_SPEEDUP if speedup is None else speedup
    return "bfloat16" if min(seconds["float32"]) >= speedup * min(seconds["bfloat16"]) else "float32"


def interleaved_cpu_seconds(candidates: dict[str, Callable[[], None]], rounds: int) -> dict[str, list[float]]:
    """The CPU seconds of each candidate in each of `rounds` rounds, after one untimed round (warm-up).

    Each round runs every candidate once, in turn, the order reversed every other round, so that a slow spell
    hits all alike. On one torch thread, timed by this thread's CPU clock: what the work costs, not how long
    a neighbour holds the core meanwhile (wall time under time-slicing; with two threads, the OpenMP team also
    waits for its slowest member). bfloat16 against float32 is a property of the arithmetic per core, so the
    one-thread ratio is the one that decides."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    names = list(candidates)
    seconds: dict[str, list[float]] = {name: [] for name in names}
    try:
        for round_ in range(rounds + 1):
            for name in (names if round_ % 2 == 0 else names[::-1]):
                started = time.thread_time()
                candidates[name]()
                if round_:
                    seconds[name].append(time.thread_time() - started)
    finally:
        torch.set_num_threads(threads)
    return seconds


def choose_update_path(learner: DoubleQLearner, batch: TraceTensors, rounds: int = 2) -> str:
    """The fastest update path for this learner's device, sizes and threads, measured once per process.

    Whole updates (soft update, passes, backward, Adam) on a scratch copy of the
    learner, so the learner itself is left as it was; each round times one update
    of each path in turn, after one untimed update each; the shortest best round wins.
    """
    threads = torch.get_num_threads()
    key = (learner.device.type, learner.device.index, dataclasses.astuple(learner.network_config),
           tuple(batch.observations.shape), threads, learner.precision)
    if key in _chosen_paths:
        return _chosen_paths[key]
    scratch = learner.scratch_copy()
    best = {name: math.inf for name in candidate_paths(learner.device, threads, learner.precision)}
    for round_ in range(rounds + 1):
        for name in best:
            scratch.use_path(name)
            _synchronize(learner.device)
            started = time.perf_counter()
            scratch._update(batch, with_q_after=False)
            _synchronize(learner.device)
            if round_:
                best[name] = min(best[name], time.perf_counter() - started)
    del scratch
    chosen = min(best, key=best.get)
    log.info("update path: %s (best of %d updates each with %d torch threads: %s)", chosen, rounds, threads,
             ", ".join(f"{name} {1e3 * seconds:.1f} ms" for name, seconds in best.items()))
    _chosen_paths[key] = chosen
    return chosen




def _synchronize(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)

