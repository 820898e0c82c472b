"""Every update path against an independent float64 reference written here from the formulas (docs/method.md,
"The update"), and the properties the paths share checked directly, each where it can break:

- n-step targets on every path (trace, trace-split, autograd), from the zero state and from a stored one;
- the target network's pass starts from the stored state;
- the stored rows are (h, c) in that order;
- no gradient reaches the burn-in frames, seen on the frames' own gradients;
- under learner.precision bfloat16 the convolutions and the LSTM input projection compute in bfloat16.

The reference shares no code with learner/update.py or common/network.py: its convolutions, LSTM, dueling head,
n-step targets and loss are written out below, in float64. Each comparison also checks that the reference with
the property broken (one-step targets, a zero target start, h and c swapped) lies far outside the tolerance, so
the test is shown to be able to tell the difference it claims to.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from torch.utils._python_dispatch import TorchDispatchMode

import common.network as network_module
from common import cpu_capability
from common.config import LearnerConfig
from common.stored_state import lstm_state, state_row
from common.trace_pass import scale_frames
from learner.update import DoubleQLearner
from tests.test_update import TINY, one_torch_thread, random_batch  # noqa: F401 (an autouse fixture)

PATHS = ["trace", "trace-split", "autograd"]
PAPER_N_STEP = LearnerConfig(n_step=3)  # zero start, n_mask 7; three-step targets
STORED_N_STEP = LearnerConfig(n_step=3, stored_state=True, burn_in=2)  # stored start, 2 steps of burn-in
STRIDES = (4, 2, 1)  # the three VALID convolutions of the D3RQN (docs/method.md, "The network")


# --- the reference, float64 ------------------------------------------------------------------------------------

def float64_parameters(network: torch.nn.Module) -> dict[str, torch.Tensor]:
    return {name: p.detach().double().clone().requires_grad_(True) for name, p in network.named_parameters()}


def reference_q_values(w: dict[str, torch.Tensor], frames: np.ndarray, start: tuple[np.ndarray, np.ndarray] | None,
                       no_grad_steps: int = 0) -> torch.Tensor:
    """Q(h_t, .) for t = 0..T of uint8 frames (B, T + 1, H, W, C): conv-ReLU x 3, an LSTM written out from
    PyTorch's gate layout (i, f, g, o), Q = V + A - mean(A). `start`: (h, c) each (B, units), or zeros.
    The first no_grad_steps steps run without gradient and hand on their state without it."""
    batch, steps = frames.shape[:2]
    x = torch.from_numpy(frames).double().div(255.0).reshape(batch * steps, *frames.shape[2:]).permute(0, 3, 1, 2)
    for name, stride in zip(("conv.0.weight", "conv.2.weight", "conv.4.weight"), STRIDES):
        x = torch.relu(F.conv2d(x, w[name], stride=stride))
    features = x.reshape(batch, steps, -1)
    units = w["lstm.weight_hh_l0"].shape[1]
    if start is None:
        h, c = torch.zeros(batch, units, dtype=torch.float64), torch.zeros(batch, units, dtype=torch.float64)
    else:
        h, c = (torch.from_numpy(np.asarray(s, dtype=np.float64)) for s in start)
    q_values = []
    for t in range(steps):
        with torch.set_grad_enabled(t >= no_grad_steps):
            z = (features[:, t] @ w["lstm.weight_ih_l0"].T + h @ w["lstm.weight_hh_l0"].T
                 + w["lstm.bias_ih_l0"] + w["lstm.bias_hh_l0"])
            i, f, g, o = z.chunk(4, dim=-1)
            c = torch.sigmoid(f) * c + torch.sigmoid(i) * torch.tanh(g)
            h = torch.sigmoid(o) * torch.tanh(c)
            advantage = h[:, :units // 2] @ w["advantage.weight"].T
            value = h[:, units // 2:] @ w["value.weight"].T
            q_values.append(value + advantage - advantage.mean(dim=-1, keepdim=True))
    return torch.stack(q_values, dim=1)


def reference_n_step_targets(rewards: np.ndarray, terminated: np.ndarray, next_online: np.ndarray,
                             next_target: np.ndarray, gamma: float, n_step: int) -> np.ndarray:
    """y_t = sum_k gamma^k r_t+k up to n_step rewards, stopped by a terminal (then no bootstrap) or by the trace's
    end; else + gamma^m Q_target(h_t+m, argmax Q_online(h_t+m)). next_*[:, j] holds Q(h_j+1, .)."""
    batch, steps = rewards.shape
    targets = np.zeros((batch, steps))
    for b in range(batch):
        for t in range(steps):
            total, k = 0.0, 0
            while True:
                total += gamma ** k * rewards[b, t + k]
                if terminated[b, t + k]:
                    break
                if k + 1 == n_step or t + k + 1 == steps:
                    total += gamma ** (k + 1) * next_target[b, t + k, np.argmax(next_online[b, t + k])]
                    break
                k += 1
            targets[b, t] = total
    return targets


@dataclasses.dataclass
class Reference:
    loss: float
    gradients: dict[str, torch.Tensor]


def reference_update(learner: DoubleQLearner, batch, *, n_step: int | None = None, target_from_zero: bool = False,
                     swap_h_c: bool = False) -> Reference:
    """The loss and gradients the learner's next update should compute, from its weights before that update.
    The keyword arguments break one property on purpose, for the tests' sensitivity checks."""
    config = learner.config
    n_step = config.n_step if n_step is None else n_step
    online = float64_parameters(learner.online)
    # the update moves the target by tau towards the online net before its pass (soft update first)
    target = {name: (1 - config.tau) * t + config.tau * online[name].detach()
              for name, t in float64_parameters(learner.target).items()}
    start = None
    if config.stored_state:
        rows = np.asarray(batch.initial_state, dtype=np.float64)
        start = (rows[:, 1], rows[:, 0]) if swap_h_c else (rows[:, 0], rows[:, 1])
    burn_in = config.burn_in if config.stored_state else 0
    masked = config.masked_steps
    q_all = reference_q_values(online, batch.observations, start, no_grad_steps=burn_in)
    with torch.no_grad():
        target_q = reference_q_values(target, batch.observations, None if target_from_zero else start)
    targets = reference_n_step_targets(batch.rewards.astype(np.float64), batch.terminated.astype(bool),
                                       q_all[:, 1:].detach().numpy(), target_q[:, 1:].numpy(), config.gamma, n_step)
    taken = q_all[:, :-1].gather(-1, torch.from_numpy(np.asarray(batch.actions))[..., None].long())[..., 0]
    errors = (torch.from_numpy(targets) - taken)[:, masked:] ** 2
    loss = errors.sum() / taken.numel()
    loss.backward()
    return Reference(loss.item(), {name: p.grad for name, p in online.items()})


# --- tolerances, from float32 rounding --------------------------------------------------------------------------
#
# The learner computes in float32 (unit roundoff u = 2^-24 ~ 6e-8), the reference in float64 (its own error,
# ~1e-16, is nothing here). A float32 sum of n terms errs by ~sqrt(n) u relative to its terms' magnitudes (random
# signs); the longest reductions of the tiny net are the first convolution (8 x 8 x 3 = 192 terms) and the LSTM
# input projection (576 features), ~25 u each, which the 11 LSTM steps pass on without growing (|f| < 1). So the
# Q-values, the loss (a mean of 30 squared errors) and the gradients (sums over those errors and up to 110 frames)
# err by ~1e-6 relative to their scale. Measured, seeds 41-44, all paths, both starts: the loss within 1.1e-7
# relative; the gradients within 3.0e-6 of each tensor's largest element, except where a ReLU input lies within
# rounding of 0 and float32 and float64 take different sides of the kink (seed 44: 2e-3; not used below).
# LOSS_RTOL = 1e-5 is ~100x the loss's rounding; GRAD_SCALED_ATOL = 1e-4, ~30x the gradients'. Each property the
# tests pin moves the reference loss by 1.7e-3 relative or more on the seeds used, SENSITIVITY = 100 tolerances
# (checked in each test, so a seed too weak to tell would fail, not pass).
LOSS_RTOL = 1e-5
GRAD_SCALED_ATOL = 1e-4
SENSITIVITY = 100  # a broken property must move the reference loss this many tolerances away


def assert_matches_reference(loss: float, gradients: dict[str, torch.Tensor], reference: Reference) -> None:
    assert loss == pytest.approx(reference.loss, rel=LOSS_RTOL)
    for name, expected in reference.gradients.items():
        scale = expected.abs().max().item()
        np.testing.assert_allclose(gradients[name].double().numpy(), expected.numpy(), rtol=0,
                                   atol=GRAD_SCALED_ATOL * scale, err_msg=name)


def assert_far_from(reference: Reference, broken: Reference) -> None:
    assert abs(broken.loss - reference.loss) > SENSITIVITY * LOSS_RTOL * reference.loss, \
        "the broken reference is too close to tell apart: the test would not notice"


def learner_with_distinct_target(path: str, config: LearnerConfig) -> DoubleQLearner:
    learner = DoubleQLearner(TINY, dataclasses.replace(config, update_path=path))
    with torch.no_grad():  # a target unlike the online net, so that mixing up their passes would show
        for k, parameter in enumerate(learner.target.parameters()):
            parameter.mul_(1.5 if k % 2 else -0.8)
    return learner


def stored_batch(seed: int):
    """A stored-state batch with a terminal inside the traces and states of both signs, c up to |c| = 3 (an
    episode's cell grows by less than 1 a step), so that the start state matters for every step."""
    rng = np.random.default_rng(seed)
    batch = random_batch(rng, terminal_last=True, stored_state=True)
    terminated = batch.terminated.copy()
    terminated[::3, 5] = True  # mid-trace terminals: the n-step sums stop there
    rows = batch.initial_state.astype(np.float32)
    rows[:, 1] *= 3.0
    return dataclasses.replace(batch, terminated=terminated, initial_state=rows.astype(np.float16))


def zero_start_batch(seed: int):
    batch = stored_batch(seed)
    return dataclasses.replace(batch, initial_state=None)


def update_and_gradients(learner: DoubleQLearner, batch) -> tuple[float, dict[str, torch.Tensor]]:
    """One update; the loss it reports and the gradients it stepped with (left in .grad by the step)."""
    torch.set_num_threads(2 if learner.update_path == "trace-split" else 1)  # split: one thread for each pass
    try:
        loss = learner.update(batch).loss
    finally:
        torch.set_num_threads(1)
    return loss, {name: p.grad.detach().clone() for name, p in learner.online.named_parameters()}


# --- n-step targets, the target's start state and h/c order, on every path -------------------------------------

@pytest.mark.parametrize("path", PATHS)
@pytest.mark.parametrize("config, make_batch", [(PAPER_N_STEP, zero_start_batch), (STORED_N_STEP, stored_batch)],
                         ids=["zero-start", "stored-state"])
def test_every_path_computes_the_n_step_loss_and_gradients_of_the_float64_reference(path, config, make_batch):
    learner = learner_with_distinct_target(path, config)
    batch = make_batch(41)
    reference = reference_update(learner, batch)
    assert_far_from(reference, reference_update(learner, batch, n_step=1))  # n-step targets matter here
    loss, gradients = update_and_gradients(learner, batch)
    assert learner.update_path == path
    assert_matches_reference(loss, gradients, reference)


@pytest.mark.parametrize("path", PATHS)
@pytest.mark.parametrize("broken, seed", [({"target_from_zero": True}, 42), ({"swap_h_c": True}, 43)],
                         ids=["the-target-pass-starts-from-the-stored-state", "the-rows-are-h-then-c"])
def test_every_path_uses_the_stored_state_as_the_reference_does(path, broken, seed):
    """The target network's pass starts from the stored state, not from zero; and the rows are read as (h, c)."""
    learner = learner_with_distinct_target(path, STORED_N_STEP)
    batch = stored_batch(seed)
    reference = reference_update(learner, batch)
    assert_far_from(reference, reference_update(learner, batch, **broken))
    loss, gradients = update_and_gradients(learner, batch)
    assert_matches_reference(loss, gradients, reference)


def test_lstm_state_reads_row_0_as_h_and_row_1_as_c_as_state_row_writes_them():
    rows = torch.tensor([[[0.25, -0.5], [2.0, -3.0]], [[0.75, 0.125], [-1.5, 4.0]]])  # (B = 2, (h, c), units = 2)
    hidden, cell = lstm_state(rows)
    torch.testing.assert_close(hidden, torch.tensor([[[0.25, -0.5], [0.75, 0.125]]]))
    torch.testing.assert_close(cell, torch.tensor([[[2.0, -3.0], [-1.5, 4.0]]]))
    row = state_row(torch.tensor([0.5, -0.25]), torch.tensor([3.0, -2.0]))
    np.testing.assert_array_equal(row, np.array([[0.5, -0.25], [3.0, -2.0]], dtype=np.float16))
    hidden, cell = lstm_state(torch.from_numpy(row[None]))
    assert hidden.tolist() == [[[0.5, -0.25]]] and cell.tolist() == [[[3.0, -2.0]]]


# --- no gradient through burn-in, seen on the frames' gradients -------------------------------------------------

def frame_gradients_of_a_trace_path(learner: DoubleQLearner, batch) -> torch.Tensor:
    """|d loss / d pixels| summed per step (T + 1,), the trace paths: the staged pixels made a leaf with grad."""
    tensors = learner.prepare(batch)
    pixels = scale_frames(tensors.observations, learner.online.used_frame_size).requires_grad_(True)
    update_and_gradients(learner, dataclasses.replace(tensors, pixels=pixels))
    traces = tensors.actions.shape[0]
    return pixels.grad.abs().reshape(-1, traces, *pixels.shape[1:]).flatten(1).sum(1)  # time-major rows


def frame_gradients_of_the_autograd_path(learner: DoubleQLearner, batch) -> torch.Tensor:
    """The same for the autograd path, whose input is uint8: the gradient reaching each frame's convolution
    features, caught by a forward hook on the online network's convolutions (none where they had no graph)."""
    traces = len(batch.actions)
    calls: list[torch.Tensor] = []

    def keep(module, inputs, output):
        if output.requires_grad:
            output.retain_grad()
        calls.append(output)

    handle = learner.online.conv.register_forward_hook(keep)
    try:
        update_and_gradients(learner, batch)
    finally:
        handle.remove()
    per_step = []
    for output in calls:  # batch-major calls over consecutive steps: burn-in, then the rest (or all at once)
        grad = output.grad if output.grad is not None else torch.zeros_like(output)
        per_step.append(grad.abs().reshape(traces, -1, *grad.shape[1:]).flatten(2).sum((0, 2)))
    return torch.cat(per_step)


@pytest.mark.parametrize("path", PATHS)
def test_no_gradient_reaches_the_burn_in_frames_on_any_path(path):
    learner = learner_with_distinct_target(path, STORED_N_STEP)
    batch = stored_batch(44)
    if path == "autograd":
        per_step = frame_gradients_of_the_autograd_path(learner, batch)
    else:
        per_step = frame_gradients_of_a_trace_path(learner, batch)
    burn_in, steps = STORED_N_STEP.burn_in, STORED_N_STEP.trace_length
    assert per_step.shape == (steps + 1,)
    assert not per_step[:burn_in].any(), per_step  # exactly zero: no graph through burn-in
    assert (per_step[burn_in:steps] > 0).all(), per_step  # the trained steps' frames do get gradient


def test_the_paper_zero_start_passes_gradient_through_its_masked_steps():
    """The paper's masked steps (zero start, no burn-in) are part of the graph: their frames get gradient
    through the LSTM from the later errors. The burn-in test above would pass vacuously if the hooks saw none."""
    for path in ("trace", "autograd"):
        learner = learner_with_distinct_target(path, PAPER_N_STEP)
        batch = zero_start_batch(45)
        per_step = (frame_gradients_of_the_autograd_path(learner, batch) if path == "autograd"
                    else frame_gradients_of_a_trace_path(learner, batch))
        assert (per_step[:PAPER_N_STEP.trace_length] > 0).all(), (path, per_step)


# --- the dtypes actually computed under learner.precision bfloat16 ----------------------------------------------

class OpDtypes(TorchDispatchMode):
    """Records (op name, output dtype, input shapes) of every aten op run inside it."""

    def __init__(self):
        super().__init__()
        self.seen: list[tuple[str, torch.dtype, list[tuple[int, ...]]]] = []

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        out = func(*args, **(kwargs or {}))
        first = out[0] if isinstance(out, (tuple, list)) else out
        if isinstance(first, torch.Tensor):
            shapes = [tuple(a.shape) for a in args if isinstance(a, torch.Tensor)]
            self.seen.append((str(func.overloadpacket.__name__), first.dtype, shapes))
        return out


def computed_dtypes(learner: DoubleQLearner, batch) -> dict[str, set[torch.dtype]]:
    """The output dtypes of one update's convolutions (forward and backward), LSTM input projections (the
    GEMMs whose weight is (4 units, features)) and recurrent products."""
    features, units = learner.online.n_features, learner.online.lstm_units
    with OpDtypes() as ops:
        learner.update(batch)
    kinds: dict[str, set[torch.dtype]] = {"convolution": set(), "convolution backward": set(), "projection": set(),
                                          "recurrence": set()}
    for name, dtype, shapes in ops.seen:
        if name in ("convolution", "_convolution_pointwise"):
            kinds["convolution"].add(dtype)
        elif name == "convolution_backward":
            kinds["convolution backward"].add(dtype)
        elif name in ("addmm", "mm") and ((4 * units, features) in shapes or (features, 4 * units) in shapes):
            kinds["projection"].add(dtype)
        elif name in ("addmm", "mm") and (4 * units, units) in shapes:
            kinds["recurrence"].add(dtype)
    return kinds


def precision_learner(precision: str) -> DoubleQLearner:
    return DoubleQLearner(TINY, LearnerConfig(precision=precision, update_path="trace"))


@pytest.fixture(params=["oneDNN fused", "unfused"])
def bfloat16_convolutions(request, monkeypatch):
    """The convolutions the bfloat16 pass can use. oneDNN's fused convolution with ReLU is the one bfloat16 op
    that a CPU without AVX-512 (this project's AMD EPYC) refuses; the plain convolution, its backward and the
    GEMMs run in bfloat16 anywhere (emulated, slowly). So the unfused variant runs here too, and checks on
    every machine that bfloat16 is what gets computed; the fused one needs the real thing."""
    if request.param == "unfused":
        monkeypatch.setattr(network_module, "fused_relu_convolution_available", lambda device: False)
        monkeypatch.setattr(cpu_capability, "bfloat16_problem", lambda: None)  # the op that fails is not used
    elif cpu_capability.bfloat16_problem() is not None:
        pytest.skip(f"bfloat16 cannot run on this CPU: {cpu_capability.bfloat16_problem()}")
    return request.param


def test_bfloat16_computes_the_convolutions_and_projection_in_bfloat16(bfloat16_convolutions):
    compact = precision_learner("bfloat16")
    assert compact.precision == "bfloat16"
    kinds = computed_dtypes(compact, random_batch(np.random.default_rng(46)))
    assert kinds == {"convolution": {torch.bfloat16}, "convolution backward": {torch.bfloat16},
                     "projection": {torch.bfloat16}, "recurrence": {torch.float32}}, kinds
    assert all(p.grad.dtype == torch.float32 for p in compact.online.parameters())  # master gradients float32


def test_float32_computes_everything_in_float32():
    kinds = computed_dtypes(precision_learner("float32"), random_batch(np.random.default_rng(46)))
    assert kinds == {"convolution": {torch.float32}, "convolution backward": {torch.float32},
                     "projection": {torch.float32}, "recurrence": {torch.float32}}, kinds

