"""Learner updates per second against the machine's measured peak, with a per-phase breakdown.

In one run, on one batch and the same initial weights for every variant:

1. the FLOPs of one update, counted from the network's shapes (deploy/bench/flops.py);
2. the machine's fp32 peak: a large square GEMM, and plain GEMMs of the
   update's own shapes (the LSTM projection forward and backward, the
   recurrence, the convolutions as im2col products), whose times add up to the
   ceiling the update would reach if every layer ran like a plain GEMM;
3. updates/s of today's code and of the new code, and the fraction of the
   peak they reach (FLOPs per update x updates/s / peak GFLOP/s);
4. where the time of one update goes, phase by phase.

Everything takes turns within each round (peak GEMMs, every variant, the
staged updates), so that noise from other processes hits all alike; figures
are medians over the rounds (best rounds in brackets). Warm-up excluded.
Sizes come from the config (paper: B = 10, T = 10, RGB 66 x 200, LSTM 512).

    .venv/bin/python deploy/bench/learner_speed.py [--threads 2] [--rounds 7] [--updates 3]
    .venv/bin/python deploy/bench/learner_speed.py --threads 1 --clock cpu   # a busy machine: CPU time of the one thread
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import torch

from common.config import Config
from common.config_cli import add_config_arguments, parse_config_or_exit
from common.cpu_capability import bfloat16_problem, describe_cpu
from common.network import D3RQN, conv_input_extent, resolve_device
from common.trace_pass import scale_frames
from common.wire.frames import FrameStack
from deploy.bench.flops import update_flops
from deploy.bench.gemm_peak import Clock, Gemms, shape_flops
from deploy.bench.reference_update import paper_reference_loss
from learner.loss import one_pass_terms, trace_pass_loss
from learner.trace_batch import TraceArrays
from learner.update import DoubleQLearner
from learner.update_path import candidate_paths

@dataclasses.dataclass(frozen=True)
class Variant:
    description: str
    path: object  # an update path (learner.update_path) or a loss function
    with_q_after: bool = False
    ahead: bool = False  # decode and stage the next batch on a thread while the update runs
    threads: int = 0  # torch threads for this variant's updates; 0: the run's
    precision: str = "float32"  # learner.precision


# "today" is the code before issue 14. Every variant decodes its batch from the wire format first.
VARIANTS = {
    "today": Variant("today: one-pass, autograd", "autograd"),
    "new": Variant("new: trace passes", "trace"),
    "split": Variant("new: trace passes, split threads", "trace-split"),
    "ahead": Variant("new: trace, staged ahead", "trace", ahead=True),
    "split-ahead": Variant("new: split, staged ahead", "trace-split", ahead=True),
    "new-1t": Variant("new: trace passes, 1 thread", "trace", threads=1),
    "today+vdbe": Variant("today + VDBE after-pass", "autograd", with_q_after=True),
    "new+vdbe": Variant("new + VDBE after-pass", "trace", with_q_after=True),
    "paper": Variant("paper reference, 3 passes", paper_reference_loss),
    "new-bf16": Variant("new: trace passes, bfloat16", "trace", precision="bfloat16"),
    "split-bf16": Variant("new: split threads, bfloat16", "trace-split", precision="bfloat16"),
}
DEFAULT_VARIANTS = "today,new,split,ahead,new+vdbe,paper,new-bf16,split-bf16"


class Runner:
    """Runs one variant's updates on the wire batch, decoding it inline or staging it ahead on a thread."""

    def __init__(self, variant: Variant, learner: DoubleQLearner, wire_frames: FrameStack, batch: TraceArrays) -> None:
        self.variant, self.learner = variant, learner
        self.wire_frames, self.batch = wire_frames, batch
        self.stager = learner.stager()
        self.thread = ThreadPoolExecutor(max_workers=1, thread_name_prefix="stage") if variant.ahead else None
        self.pending = None

    def decoded(self) -> TraceArrays:
        observations = self.wire_frames.decode().reshape(self.batch.observations.shape)
        return TraceArrays(observations, self.batch.actions, self.batch.rewards, self.batch.terminated)

    def staged(self):
        return self.stager.stage(self.decoded())

    def updates(self, count: int) -> None:
        threads = torch.get_num_threads()
        torch.set_num_threads(self.variant.threads or threads)
        try:
            self._updates(count)
        finally:
            torch.set_num_threads(threads)

    def _updates(self, count: int) -> None:
        for _ in range(count):
            if self.thread is None:
                self.learner.update(self.decoded(), with_q_after=self.variant.with_q_after)
                continue
            if self.pending is None:
                self.pending = self.thread.submit(self.staged)
            ready, self.pending = self.pending.result(), self.thread.submit(self.staged)
            self.learner.update(ready, with_q_after=self.variant.with_q_after)

    def close(self) -> None:
        if self.thread is not None:
            self.thread.shutdown()


def make_learner(config: Config, path, device: torch.device, precision: str = "float32") -> DoubleQLearner:
    if isinstance(path, str):
        learner = dataclasses.replace(config.learner, update_path=path, precision=precision)
        return DoubleQLearner(config.network, learner, device=device)
    return DoubleQLearner(config.network, config.learner, path, device=device)


def random_batch(config: Config, seed: int = 0) -> TraceArrays:
    """Blocky random frames (8 x 8 pixel tiles), which compress about as well as camera frames do."""
    rng = np.random.default_rng(seed)
    net, learner = config.network, config.learner
    steps = (learner.batch_size, learner.trace_length)
    tiles = rng.integers(0, 256, (*steps[:1], learner.trace_length + 1, net.frame_height // 8 + 1,
                                  net.frame_width // 8 + 1, net.frame_channels), dtype=np.uint8)
    frames = tiles.repeat(8, axis=2).repeat(8, axis=3)[:, :, :net.frame_height, :net.frame_width]
    return TraceArrays(observations=np.ascontiguousarray(frames), actions=rng.integers(0, net.n_actions, steps),
                       rewards=rng.random(steps).astype(np.float32), terminated=np.zeros(steps, bool))


# --- the phases -----------------------------------------------------------------------------

class PhaseTimer:
    def __init__(self, clock: Clock) -> None:
        self.clock = clock
        self.seconds: dict[str, float] = {}
        self._last = clock()

    def mark(self, phase: str) -> None:
        """The time since the previous mark goes to `phase`."""
        now = self.clock()
        self.seconds[phase] = self.seconds.get(phase, 0.0) + now - self._last
        self._last = now


def staged_update(learner: DoubleQLearner, wire_frames: FrameStack, batch: TraceArrays, clock: Clock,
                  with_q_after: bool) -> dict[str, float]:
    """learner.update(batch) step by step, timing each phase; the same arithmetic in the same order."""
    timer = PhaseTimer(clock)
    observations = wire_frames.decode().reshape(batch.observations.shape)
    timer.mark("frame decode (wire)")
    tensors = learner.prepare(TraceArrays(observations, batch.actions, batch.rewards, batch.terminated))
    timer.mark("copy-in and checks")
    traces, steps = batch.actions.shape
    gamma, n_mask = learner.config.gamma, learner.config.n_mask
    if learner.split_passes:
        terms = learner._split_trace_pass_loss(tensors)
        timer.mark("online forward || soft update + target forward")
        q_all, next_q_target = None, None
    elif learner.loss_function is trace_pass_loss:
        learner.soft_update_target()
        timer.mark("soft target update")
        pixels = scale_frames(tensors.observations, learner.online.used_frame_size)
        timer.mark("frame scaling")
        features = learner.online.trace_features(pixels, traces, steps)
        timer.mark("online forward: conv")
        q_all = learner.online.trace_head(features, traces, steps)
        timer.mark("online forward: lstm + head")
        with torch.no_grad():
            next_q_target = learner.target.trace_q_values(pixels, traces)[:, 1:]
        timer.mark("target forward")
    else:
        learner.soft_update_target()
        timer.mark("soft target update")
        hook = learner.online.lstm.register_forward_pre_hook(lambda *_: timer.mark("online forward: conv"))
        try:
            q_all, _ = learner.online(tensors.observations)
        finally:
            hook.remove()
        timer.mark("online forward: lstm + head")
        with torch.no_grad():
            next_q_target = learner.target(tensors.observations)[0][:, 1:]
        timer.mark("target forward")
    if q_all is not None:
        terms = one_pass_terms(q_all, next_q_target, tensors, gamma, n_mask)
        timer.mark("loss")
    learner.optimizer.zero_grad(set_to_none=True)
    terms.loss.backward()
    timer.mark("backward")
    learner.optimizer.step()
    timer.mark("Adam")
    learner.updates += 1
    learner.exploration_terms(tensors, terms, with_q_after=False)
    timer.mark("exploration hooks (Q, BMC returns)")
    if with_q_after:
        greedy = terms.q_values[:, n_mask:].argmax(dim=-1)
        learner._greedy_q_after(tensors, greedy)
        timer.mark("VDBE after-pass")
    return timer.seconds


# --- the run --------------------------------------------------------------------------------

def median(values: list[float]) -> float:
    return statistics.median(values)


def run(config: Config, variants: list[str], rounds: int, updates: int, warmup: int, clock_kind: str,
        square: int, with_phases: bool) -> None:
    device = resolve_device(config.network)
    clock = Clock(clock_kind, device)
    net, learner_config = config.network, config.learner
    flops = update_flops(net, learner_config)
    flops_vdbe = update_flops(net, learner_config, with_q_after=True)
    update_gflop = sum(flops.values()) / 1e9
    executed_today = sum(update_flops(net, learner_config, backward_steps=learner_config.trace_length + 1).values())
    used_height, used_width = conv_input_extent(net.frame_height, net.frame_width)
    cropped = dataclasses.replace(net, frame_height=used_height, frame_width=used_width)
    executed_new = sum(update_flops(cropped, learner_config).values())

    print(f"\nFLOPs of one update (multiply-adds x 2 of convolutions and matrix products; deploy/bench/flops.py)")
    for phase, value in flops.items():
        print(f"  {phase:34s} {value / 1e9:7.3f} GFLOP")
    print(f"  {'total':34s} {update_gflop:7.3f} GFLOP   (+ VDBE after-pass "
          f"{flops_vdbe['VDBE after-pass'] / 1e9:.3f})")
    print(f"  executed by today's code, which also back-propagates through s_T: {executed_today / 1e9:.3f} GFLOP; "
          f"by the new code, which skips the {net.frame_height - used_height} bottom rows and "
          f"{net.frame_width - used_width} right columns no convolution output reads: {executed_new / 1e9:.3f} GFLOP")
    print("  fractions of peak below count the total above for every variant, against the peak at the run's "
          "thread count", flush=True)

    batch = random_batch(config)
    wire_frames = FrameStack.from_array(batch.observations.reshape(-1, *batch.observations.shape[2:]))
    gemms = Gemms(config, device, square)
    runners = {name: Runner(VARIANTS[name], make_learner(config, VARIANTS[name].path, device, VARIANTS[name].precision), wire_frames, batch)
               for name in variants}
    staged = {name: make_learner(config, path, device)
              for name, path in (("today", "autograd"), ("new", "trace"), ("split", "trace-split"))
              if path in candidate_paths(device, torch.get_num_threads())} if with_phases else {}

    for runner in runners.values():
        runner.updates(warmup)
    for path, learner in staged.items():
        for _ in range(warmup):
            staged_update(learner, wire_frames, batch, clock, with_q_after=False)
    gemms.square_seconds(clock)
    gemms.shape_seconds(clock)

    square_gflops: list[float] = []
    shape_times: dict[str, list[float]] = {name: [] for name in gemms.shapes}
    rates: dict[str, list[float]] = {name: [] for name in variants}
    phases: dict[str, dict[str, list[float]]] = {path: {} for path in staged}
    for round_ in range(rounds):
        square_gflops.append(2.0 * square ** 3 / gemms.square_seconds(clock) / 1e9)
        for name, seconds in gemms.shape_seconds(clock).items():
            shape_times[name].append(seconds)
        for name, runner in runners.items():
            rates[name].append(updates / clock.seconds(lambda: runner.updates(updates)))
        for path, learner in staged.items():
            for phase, seconds in staged_update(learner, wire_frames, batch, clock, with_q_after=True).items():
                phases[path].setdefault(phase, []).append(seconds)
        progress = ", ".join(f"{name} {values[-1]:.2f}/s" for name, values in rates.items())
        print(f"  round {round_ + 1}/{rounds}: square GEMM {square_gflops[-1]:.0f} GFLOP/s; {progress}", flush=True)

    for runner in runners.values():
        runner.close()
    peak = median(square_gflops)
    print(f"\npeak fp32 GEMM, {torch.get_num_threads()} threads, {clock_kind} clock")
    print(f"  square {square}x{square}x{square}: median {peak:.1f} GFLOP/s (best {max(square_gflops):.1f})")
    ceiling_seconds = 0.0
    weights = shape_flops(config)
    for name in gemms.shapes:
        seconds = median(shape_times[name])
        rate = gemms.shape_gflops(name, seconds)
        ceiling_seconds += weights[name] / (rate * 1e9)
        m, k, n, calls, _ = gemms.shapes[name]
        repeat = f" x{calls} in sequence" if calls > 1 else ""
        print(f"  {name:32s} {m:6d} x {k:5d} x {n:5d}{repeat:17s} {rate:7.1f} GFLOP/s ({100 * rate / peak:3.0f}% of square)")
    timed = sum(weights[name] for name in gemms.shapes)
    ceiling_gflops = timed / ceiling_seconds / 1e9
    print(f"  the update's GEMM-shape ceiling: {ceiling_gflops:.1f} GFLOP/s ({100 * ceiling_gflops / peak:.0f}% of "
          f"square) = {ceiling_gflops / update_gflop:.2f} updates/s if every layer ran like a plain GEMM of its shape")

    print(f"\nupdates per second, each from a batch decoded from the wire format (median, best round in brackets)")
    for name, values in rates.items():
        gflop = sum((flops_vdbe if VARIANTS[name].with_q_after else flops).values()) / 1e9
        achieved = gflop * median(values)
        print(f"  {VARIANTS[name].description:32s} {median(values):6.2f} [{max(values):6.2f}]  {1e3 / median(values):6.1f} ms  "
              f"{achieved:6.1f} GFLOP/s = {100 * achieved / peak:4.1f}% of peak, "
              f"{100 * achieved / ceiling_gflops:4.1f}% of the GEMM-shape ceiling")
    if "today" in rates and "new" in rates:
        today, new = rates["today"], rates["new"]
        print(f"  new / today: {median(new) / median(today):.3f} by medians, {max(new) / max(today):.3f} by best rounds")

    if staged:
        print(f"\nphases of one update, ms (median over rounds; update() step by step, with VDBE's after-pass)")
        names = list(dict.fromkeys(name for path in phases.values() for name in path))
        print(f"  {'phase':48s} " + " ".join(f"{path:>9s}" for path in phases))
        for name in names:
            cells = [f"{1e3 * median(phases[path][name]):9.2f}" if name in phases[path] else f"{'-':>9s}"
                     for path in phases]
            print(f"  {name:48s} " + " ".join(cells))
        totals = [sum(median(values) for values in path.values()) for path in phases.values()]
        print(f"  {'sum':48s} " + " ".join(f"{1e3 * total:9.2f}" for total in totals))


def bench_actor_steps(config: Config, steps: int, repeats: int) -> list[float]:
    """Single-frame forward passes per second, batch 1, carrying the LSTM state."""
    device = resolve_device(config.network)
    network = D3RQN(config.network).to(device).eval()
    net = config.network
    frames = torch.randint(0, 256, (steps, 1, 1, net.frame_height, net.frame_width, net.frame_channels),
                           dtype=torch.uint8, device=device)
    rates = []
    with torch.inference_mode():
        for repeat in range(repeats + 1):  # the first round warms up
            state = network.initial_state(1)
            started = time.perf_counter()
            for frame in frames:
                q_values, state = network(frame, state)
                q_values.cpu()
            if repeat:
                rates.append(steps / (time.perf_counter() - started))
    return rates


def describe_machine(device: torch.device) -> str:
    return torch.cuda.get_device_name(device) if device.type == "cuda" else describe_cpu()


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="learner_speed", description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=0, help="torch threads (default: torch's default)")
    parser.add_argument("--rounds", type=int, default=7, help="rounds; every measurement once per round (default 7)")
    parser.add_argument("--updates", type=int, default=3, help="updates per variant per round (default 3)")
    parser.add_argument("--warmup", type=int, default=2, help="untimed updates per variant first (default 2)")
    parser.add_argument("--clock", choices=("wall", "cpu"), default="wall",
                        help="wall time, or the process's CPU time: steadier on a busy machine, but with more "
                             "than one thread it also counts threads spinning while they wait (default wall)")
    parser.add_argument("--square", type=int, default=0,
                        help="size of the square GEMM (default 2048 on CPU, 8192 on CUDA)")
    parser.add_argument("--variants", default=DEFAULT_VARIANTS,
                        help="comma-separated, of: " + "; ".join(f"{key} ({v.description})" for key, v in VARIANTS.items())
                        + f" (default: {DEFAULT_VARIANTS})")
    parser.add_argument("--no-phases", action="store_true", help="skip the per-phase breakdown")
    parser.add_argument("--actor-steps", type=int, default=300, help="single steps per actor round; 0 skips (default 300)")
    add_config_arguments(parser)
    args, config = parse_config_or_exit(parser, argv)
    variants = [name.strip() for name in args.variants.split(",") if name.strip()]
    unknown = [name for name in variants if name not in VARIANTS]
    if unknown:
        parser.error(f"unknown variants {unknown}; choose from {list(VARIANTS)}")
    if bfloat16_problem() is not None and resolve_device(config.network).type == "cpu":
        skipped = [name for name in variants if VARIANTS[name].precision == "bfloat16"]
        variants = [name for name in variants if name not in skipped]
        if skipped:
            print(f"skipping {', '.join(skipped)}: {bfloat16_problem()}")
    if args.threads:
        torch.set_num_threads(args.threads)
    net, learner = config.network, config.learner
    device = resolve_device(net)

    print(f"torch {torch.__version__}, device {device} ({describe_machine(device)}), "
          f"torch.get_num_threads() = {torch.get_num_threads()}")
    print(f"batch B={learner.batch_size} T={learner.trace_length} frames {net.frame_height}x{net.frame_width}"
          f"x{net.frame_channels}, LSTM {net.lstm_units}; {args.rounds} rounds x {args.updates} updates per variant "
          f"after {args.warmup} warm-up updates; {args.clock} clock", flush=True)
    square = args.square or (8192 if device.type == "cuda" else 2048)
    run(config, variants, args.rounds, args.updates, args.warmup, args.clock, square, not args.no_phases)

    if args.actor_steps:
        print(f"\nactor single-step inference (batch 1, one frame, state carried, inference_mode)", flush=True)
        steps = bench_actor_steps(config, args.actor_steps, args.rounds)
        print(f"  steps per second: median {median(steps):.1f}, best {max(steps):.1f}")


if __name__ == "__main__":
    main()
