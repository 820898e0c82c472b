"""What this CPU is and what it can compute: its model and flags, and whether bfloat16 runs here.

The machines this project runs on differ: an Intel Xeon with AMX runs the
bfloat16 passes natively; an AMD EPYC (Zen 3, AVX2 only) has no bfloat16 path
at all in PyTorch's oneDNN, which refuses a bfloat16 convolution outright. So
every place that may pick bfloat16 asks `bfloat16_problem()` first. It is probed
once per process, by a tiny trial of the operations the bfloat16 passes use (a
convolution forward and backward, the fused convolution with ReLU, a matrix
product), not by catching an error in the middle of a run. Where the trial fails
the CPU flags name what is missing.

To see the fallback on a machine that has bfloat16, cap oneDNN below it:
`ONEDNN_MAX_CPU_ISA=AVX2` makes its bfloat16 convolutions fail as they do on a
CPU without AVX-512, and the probe reports bfloat16 as absent.
"""

from __future__ import annotations

import functools
import sys

# oneDNN's bfloat16 convolutions need one of these sets of flags (its message on a CPU without them).
ONEDNN_BFLOAT16_FLAGS = (("avx512bw", "avx512vl", "avx512dq"), ("avx_ne_convert",))
NATIVE_BFLOAT16_FLAGS = ("avx512_bf16", "amx_bf16")  # bfloat16 arithmetic in hardware, not emulated
SHOWN_FLAGS = {"AVX2": "avx2", "AVX-512": "avx512f", "AVX512-BF16": "avx512_bf16", "AMX": "amx_bf16"}


class PrecisionUnavailable(ValueError):
    """A precision asked for by name cannot run on this CPU; the message names the option and why."""


@functools.cache
def _cpuinfo() -> tuple[str, frozenset[str] | None]:
    """The CPU's model name and flags from /proc/cpuinfo; flags None where it cannot be read."""
    model, flags = "", None
    try:
        with open("/proc/cpuinfo") as cpuinfo:
            for line in cpuinfo:
                name, _, value = line.partition(":")
                if name.strip() == "model name" and not model:
                    model = value.strip()
                elif name.strip() == "flags" and flags is None:
                    flags = frozenset(value.split())
    except OSError:
        pass
    return model or "unknown CPU", flags


def cpu_model() -> str:
    return _cpuinfo()[0]


def cpu_flags() -> frozenset[str] | None:
    return _cpuinfo()[1]


def cpu_label() -> str:
    """The model and the widest of its vector extensions that matter here ("AMD EPYC, AVX512-BF16"): two
    machines with one model name can differ in them, and so in speed and in the learner's precision."""
    flags = cpu_flags() or frozenset()
    widest = next((name for name, flag in reversed(SHOWN_FLAGS.items()) if flag in flags), None)
    return cpu_model() if widest is None else f"{cpu_model()}, {widest}"


def describe_cpu() -> str:
    """One line for benchmarks and reports: the model, the flags that matter here, and bfloat16's verdict."""
    flags = cpu_flags()
    shown = ("flags unknown" if flags is None else
             ", ".join(f"{name} {'yes' if flag in flags else 'no'}" for name, flag in SHOWN_FLAGS.items()))
    problem = bfloat16_problem()
    return f"{cpu_model()} ({shown}; bfloat16 compute: {'runs' if problem is None else 'absent'})"


def bfloat16_native() -> bool:
    """Whether the CPU does bfloat16 arithmetic in hardware (AVX512-BF16 or AMX), not just converts."""
    flags = cpu_flags() or frozenset()
    return bfloat16_problem() is None and any(flag in flags for flag in NATIVE_BFLOAT16_FLAGS)


@functools.cache
def bfloat16_problem() -> str | None:
    """None where the bfloat16 passes run on this CPU; otherwise why not, in one line."""
    try:
        _bfloat16_trial()
    except RuntimeError as error:
        return _missing_flags() or str(error).strip().splitlines()[0]
    return None


def _bfloat16_trial() -> None:
    import torch  # here: a process that asks for float32 only never waits for torch on this account

    from common.trace_pass import conv_relu, fused_relu_convolution_available
    pixels = torch.ones(1, 3, 8, 8, dtype=torch.bfloat16, requires_grad=True)
    weight = torch.ones(4, 3, 3, 3, dtype=torch.bfloat16, requires_grad=True)
    torch.nn.functional.conv2d(pixels, weight, stride=2).sum().backward()
    with torch.no_grad():
        conv_relu(pixels.detach(), weight.detach(), 2, fused_relu_convolution_available(torch.device("cpu")))
        torch.addmm(torch.ones(4, dtype=torch.bfloat16), torch.ones(2, 3, dtype=torch.bfloat16),
                    torch.ones(3, 4, dtype=torch.bfloat16))


def _missing_flags() -> str | None:
    """Which flags oneDNN's bfloat16 path needs and this CPU lacks; None if the flags cannot tell."""
    flags = cpu_flags()
    if flags is None or any(all(flag in flags for flag in needed) for needed in ONEDNN_BFLOAT16_FLAGS):
        return None
    wanted = " or ".join("+".join(needed) for needed in ONEDNN_BFLOAT16_FLAGS)
    return f"this CPU ({cpu_model()}) lacks the {wanted} instructions that bfloat16 convolutions need"


def require_precision(option: str, precision: str) -> None:
    """Refuses an explicit bfloat16 that this CPU cannot run: PrecisionUnavailable naming the option."""
    problem = bfloat16_problem() if precision == "bfloat16" else None
    if problem is not None:
        raise PrecisionUnavailable(f"{option} = bfloat16 cannot run here: {problem}; use float32 or auto")


def exit_if_unrunnable(prog: str, precisions: dict[str, str]) -> None:
    """At a process's start: an explicit bfloat16 this CPU cannot run is one line on stderr and exit code 2."""
    for option, precision in precisions.items():
        try:
            require_precision(option, precision)
        except PrecisionUnavailable as error:
            print(f"{prog}: config error: {error}", file=sys.stderr)
            raise SystemExit(2) from None
