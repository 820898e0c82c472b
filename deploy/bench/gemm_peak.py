"""What the machine's matrix products reach, for the speed benchmarks to compare with: the one-core
square GEMM's peak, and the learner's own GEMM shapes timed alone (learner_speed.py, actor_speed.py);
and the clock they time with (wall, or the process's CPU time on a busy machine).
"""

from __future__ import annotations

import time
from typing import Callable

import torch

from common.config import Config
from common.network import CONV_LAYERS
from deploy.bench.flops import conv_features, conv_multiply_adds


class Clock:
    """Wall time, or the process's CPU time (robust on a busy machine, meaningful with one thread)."""

    def __init__(self, kind: str, device: torch.device) -> None:
        self.now = time.perf_counter if kind == "wall" else time.process_time
        self.device = device

    def __call__(self) -> float:
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
        return self.now()

    def seconds(self, work: Callable[[], object], repeat: int = 1) -> float:
        started = self()
        for _ in range(repeat):
            work()
        return (self() - started) / repeat


def gemm_shapes(config: Config) -> dict[str, tuple[int, int, int, int, str]]:
    """The update's matrix products as (m, k, n, calls in sequence, layout).

    Layout "nt" multiplies by the transpose of a row-major (n, k) matrix, as a
    linear layer's forward pass does; "tn" by the transpose of a row-major (k, m)
    one, as its weight gradient does. The convolutions appear as their im2col
    products (rows = output pixels of all frames). Each shape stands for the
    FLOPs of its layer in the forward and backward passes of one update.
    """
    net, learner = config.network, config.learner
    traces, steps = learner.batch_size, learner.trace_length + 1
    frames, grad_frames = traces * steps, traces * learner.trace_length
    units = net.lstm_units
    shapes = {}
    height, width, channels = net.frame_height, net.frame_width, net.frame_channels
    for index, (filters, kernel, stride) in enumerate(CONV_LAYERS, 1):
        height, width = (height - kernel) // stride + 1, (width - kernel) // stride + 1
        shapes[f"conv{index} as im2col GEMM"] = (frames * height * width, channels * kernel * kernel, filters, 1, "nn")
        channels = filters
    features = channels * height * width
    shapes["LSTM projection, forward"] = (frames, features, 4 * units, 1, "nt")
    shapes["LSTM projection, input grad"] = (grad_frames, 4 * units, features, 1, "nn")
    shapes["LSTM projection, weight grad"] = (4 * units, grad_frames, features, 1, "tn")
    shapes["LSTM recurrence step"] = (traces, units, 4 * units, steps, "nn")
    return shapes


def shape_flops(config: Config) -> dict[str, float]:
    """FLOPs of one update each GEMM shape stands for."""
    net, learner = config.network, config.learner
    traces, steps = learner.batch_size, learner.trace_length + 1
    frames, grad_frames = traces * steps, traces * learner.trace_length
    macs = conv_multiply_adds(net)
    units = net.lstm_units
    flops = {}
    for index, count in enumerate(macs, 1):
        backward = grad_frames * count * (1 if index == 1 else 2)
        flops[f"conv{index} as im2col GEMM"] = 2.0 * (2 * frames * count + backward)
    features = conv_features(net)
    flops["LSTM projection, forward"] = 2.0 * 2 * frames * features * 4 * units
    flops["LSTM projection, input grad"] = 2.0 * grad_frames * features * 4 * units
    flops["LSTM projection, weight grad"] = 2.0 * grad_frames * features * 4 * units
    recurrence = 2.0 * traces * units * 4 * units
    flops["LSTM recurrence step"] = recurrence * (2 * steps + 2 * learner.trace_length - 1)
    flops["dueling head (not timed)"] = 2.0 * (units // 2) * (net.n_actions + 1) * (2 * frames + 2 * grad_frames)
    return flops


class Gemms:
    """Plain matrix products on the device (fp32 unless told): the square one and the update's shapes."""

    def __init__(self, config: Config, device: torch.device, square: int, dtype: torch.dtype = torch.float32) -> None:
        self.square = square
        generator = torch.Generator().manual_seed(0)
        self.a = torch.randn(square, square, generator=generator).to(device, dtype)
        self.b = torch.randn(square, square, generator=generator).to(device, dtype)
        self.shapes = gemm_shapes(config)
        self.operands = {}
        for name, (m, k, n, calls, layout) in self.shapes.items():
            a = torch.randn(*((k, m) if layout[0] == "t" else (m, k)), generator=generator).to(device)
            b = torch.randn(*((n, k) if layout[1] == "t" else (k, n)), generator=generator).to(device)
            a, b = a.to(dtype), b.to(dtype)
            self.operands[name] = (a.t() if layout[0] == "t" else a, b.t() if layout[1] == "t" else b, calls)

    def square_seconds(self, clock: Clock) -> float:
        return clock.seconds(lambda: torch.mm(self.a, self.b), repeat=2)

    def shape_seconds(self, clock: Clock) -> dict[str, float]:
        times = {}
        for name, (a, b, calls) in self.operands.items():
            times[name] = clock.seconds(lambda: [torch.mm(a, b) for _ in range(calls)])
        return times

    def shape_gflops(self, name: str, seconds: float) -> float:
        m, k, n, calls, _ = self.shapes[name]
        return 2.0 * m * k * n * calls / seconds / 1e9
