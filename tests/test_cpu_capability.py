"""The CPU probe: what it reads, what it says where bfloat16 cannot run, and a process's refusal at start.

A CPU without bfloat16 is made here by capping oneDNN at AVX2 (ONEDNN_MAX_CPU_ISA) in a child process: its
bfloat16 convolutions then fail exactly as on an AMD EPYC without AVX-512.
"""

import os
import subprocess
import sys

import pytest

from common import cpu_capability
from tests.cpu_support import needs_bfloat16

ZEN3 = ("AMD EPYC 7B13 64-Core Processor", frozenset({"sse4_2", "avx", "avx2", "fma", "bmi2"}))
SAPPHIRE_RAPIDS = ("Intel(R) Xeon(R) Platinum 8481C", frozenset({"avx2", "avx512f", "avx512bw", "avx512vl",
                                                                "avx512dq", "avx512_bf16", "amx_bf16"}))


def without_bfloat16(code: str) -> subprocess.CompletedProcess:
    environment = {**os.environ, "ONEDNN_MAX_CPU_ISA": "AVX2"}
    return subprocess.run([sys.executable, *code.split()] if code.startswith("-m ") else [sys.executable, "-c", code],
                          env=environment, capture_output=True, text=True, timeout=120)


def test_the_missing_flags_are_named_from_the_cpus_flags(monkeypatch):
    monkeypatch.setattr(cpu_capability, "_cpuinfo", lambda: ZEN3)
    said = cpu_capability._missing_flags()
    assert said == ("this CPU (AMD EPYC 7B13 64-Core Processor) lacks the avx512bw+avx512vl+avx512dq or "
                    "avx_ne_convert instructions that bfloat16 convolutions need")
    monkeypatch.setattr(cpu_capability, "_cpuinfo", lambda: SAPPHIRE_RAPIDS)
    assert cpu_capability._missing_flags() is None  # the flags are there: the trial's own message is shown
    monkeypatch.setattr(cpu_capability, "_cpuinfo", lambda: ("unknown CPU", None))
    assert cpu_capability._missing_flags() is None


def test_the_description_names_the_model_the_flags_and_the_verdict(monkeypatch):
    monkeypatch.setattr(cpu_capability, "_cpuinfo", lambda: ZEN3)
    monkeypatch.setattr(cpu_capability, "bfloat16_problem", lambda: "absent")
    assert cpu_capability.describe_cpu() == ("AMD EPYC 7B13 64-Core Processor (AVX2 yes, AVX-512 no, "
                                             "AVX512-BF16 no, AMX no; bfloat16 compute: absent)")
    assert not cpu_capability.bfloat16_native()
    monkeypatch.setattr(cpu_capability, "_cpuinfo", lambda: SAPPHIRE_RAPIDS)
    monkeypatch.setattr(cpu_capability, "bfloat16_problem", lambda: None)
    assert cpu_capability.describe_cpu().endswith("(AVX2 yes, AVX-512 yes, AVX512-BF16 yes, AMX yes; "
                                                  "bfloat16 compute: runs)")
    assert cpu_capability.bfloat16_native()


def test_the_label_tells_apart_machines_of_one_model_name(monkeypatch):
    monkeypatch.setattr(cpu_capability, "_cpuinfo", lambda: ZEN3)
    assert cpu_capability.cpu_label() == "AMD EPYC 7B13 64-Core Processor, AVX2"
    monkeypatch.setattr(cpu_capability, "_cpuinfo", lambda: (ZEN3[0], ZEN3[1] | {"avx512f", "avx512_bf16"}))
    assert cpu_capability.cpu_label() == "AMD EPYC 7B13 64-Core Processor, AVX512-BF16"
    monkeypatch.setattr(cpu_capability, "_cpuinfo", lambda: SAPPHIRE_RAPIDS)
    assert cpu_capability.cpu_label() == "Intel(R) Xeon(R) Platinum 8481C, AMX"
    monkeypatch.setattr(cpu_capability, "_cpuinfo", lambda: ("unknown CPU", None))
    assert cpu_capability.cpu_label() == "unknown CPU"


def test_only_an_explicit_bfloat16_is_refused(monkeypatch):
    monkeypatch.setattr(cpu_capability, "bfloat16_problem", lambda: "no bfloat16 here")
    cpu_capability.require_precision("learner.precision", "float32")
    with pytest.raises(cpu_capability.PrecisionUnavailable,
                       match="^learner.precision = bfloat16 cannot run here: no bfloat16 here; use float32 or auto$"):
        cpu_capability.require_precision("learner.precision", "bfloat16")


@needs_bfloat16
def test_the_probe_finds_bfloat16_where_it_runs():
    assert cpu_capability.bfloat16_problem() is None


def test_the_probe_finds_no_bfloat16_on_a_cpu_without_it():
    child = without_bfloat16("from common import cpu_capability as c; print(c.bfloat16_problem()); "
                             "print(c.describe_cpu())")
    assert child.returncode == 0, child.stderr
    problem, description = child.stdout.splitlines()
    assert "bf16" in problem or "lacks" in problem
    assert description.endswith("bfloat16 compute: absent)")




@pytest.mark.parametrize("role, option", [("actor", "actor.inference"), ("learner", "learner.precision")])
def test_a_process_asked_for_bfloat16_on_a_cpu_without_it_stops_at_start_with_one_line(role, option):
    child = without_bfloat16(f"-m {role}.main --preset smoke --network.device cpu --{option} bfloat16")
    assert child.returncode == 2
    last = child.stderr.strip().splitlines()[-1]
    assert last.startswith(f"{role}: config error: {option} = bfloat16 cannot run here: ")
    assert "Traceback" not in child.stderr


def test_the_stack_checks_the_precisions_of_the_processes_it_starts_here():
    from common.config_values import load_config
    from deploy.launcher.stack import stack_precisions
    config = load_config("smoke", overrides={"actor.inference": "auto", "learner.precision": "bfloat16",
                                             "network.device": "cpu"})
    assert stack_precisions(config) == {"actor.inference": "auto", "learner.precision": "bfloat16"}
    config.learner.precision = "auto"  # auto falls back by itself: nothing to refuse
    assert stack_precisions(config) == {"actor.inference": "auto"}
