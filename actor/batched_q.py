"""Q-values for several simulators stepped in lockstep: one batched forward pass, one LSTM state each.

The training actor (actor/runner.py) and the evaluation workers
(actor/evaluation/episodes.py) both drive a set of simulators, "slots", with
one network. At every step the slots that are running go through the network
together; each slot's recurrent state is gathered for the pass and written
back after it, so a slot's state depends only on its own frames since it was
last reset. A batch of one is exactly the single-env forward pass.

A training actor may run its pass in bfloat16 (actor.inference): the
convolutions and the LSTM's input projection, 95% of the pass's FLOPs and 91%
of the weights it reads, take bfloat16 inputs and weights; the
recurrent product, the LSTM's state and the dueling head stay float32. On a CPU
with AMX the pass is 2.6-3.2x faster at 16-64 slots; on one without bfloat16
units it may be slower, which "auto" finds by timing both at start. Where the CPU
cannot run bfloat16 at all (common/cpu_capability.py), "auto" acts in float32 with
a log line and an explicit "bfloat16" is refused at start. The evaluation always
acts in float32: it measures the policy the learner trained.
"""

from __future__ import annotations

import logging
import statistics
import time

import numpy as np
import torch

from common import cpu_capability
from common.process_config import INFERENCE_PRECISIONS
from common.network import CONV_LAYERS, D3RQN, load_numpy_weights
from common.trace_pass import conv_relu, fused_relu_convolution_available
from common.wire.state_rows import STATE_DTYPE

# auto takes bfloat16 only when it is clearly faster: a near tie is not worth a change in the policy's numbers.
AUTO_MIN_SPEEDUP = 1.2
AUTO_TIMING_ROUNDS = 5

log = logging.getLogger("actor")


class BatchedQ:
    def __init__(self, network: D3RQN, n_slots: int, precision: str = "float32") -> None:
        if precision not in ("float32", "bfloat16"):
            raise ValueError(f"precision must be float32 or bfloat16 (auto is resolved by choose_precision), "
                             f"got {precision!r}")
        self.network = network.eval()
        self.precision = precision
        self.hidden, self.cell = network.initial_state(n_slots)
        self._compact = CompactStep(network) if precision == "bfloat16" else None

    def load_weights(self, tensors: dict[str, np.ndarray]) -> None:
        """New float32 weights for the network (and its bfloat16 copies); a ValueError changes nothing."""
        load_numpy_weights(self.network, tensors)
        if self._compact is not None:
            self._compact = CompactStep(self.network)

    @torch.no_grad()
    def reset(self, slot: int) -> None:
        """The slot starts an episode: its LSTM state is zeroed, the others' are kept."""
        self.hidden[:, slot] = 0.0
        self.cell[:, slot] = 0.0

    def state_rows(self, slots: list[int]) -> np.ndarray:
        """(len(slots), 2, lstm_units) float16: each slot's state (h, c) now, as learner.stored_state keeps it."""
        index = torch.tensor(slots)
        return torch.stack([self.hidden[0, index], self.cell[0, index]], dim=1).numpy().astype(STATE_DTYPE)

    @torch.inference_mode()
    def q_values(self, slots: list[int], observations: list[np.ndarray]) -> torch.Tensor:
        """(len(slots), n_actions): each slot's Q-values after its observation; advances those slots' states."""
        index = torch.tensor(slots)
        frames = torch.from_numpy(np.stack(observations))  # (batch, H, W, C)
        state = (self.hidden[:, index], self.cell[:, index])
        if self._compact is not None:
            q_values, (hidden, cell) = self._compact(frames, state)
        else:
            q_values, (hidden, cell) = self.network(frames.unsqueeze(1), state)  # time = 1
            q_values = q_values[:, 0]
        self.hidden[:, index] = hidden
        self.cell[:, index] = cell
        return q_values


class CompactStep:
    """One step of the D3RQN with the convolutions and the LSTM input projection in bfloat16.

    The same function as D3RQN.forward for one frame: VALID convolutions with
    ReLU, the LSTM cell (PyTorch's gate order i, f, g, o) and the dueling head.
    Only the top-left part of a frame that the convolutions read is converted.
    The copies are taken when built: new weights need a new CompactStep.
    """

    dtype = torch.bfloat16

    def __init__(self, network: D3RQN) -> None:
        self.used_frame_size = network.used_frame_size
        self.fused = fused_relu_convolution_available(torch.device("cpu"))
        self.conv_weights = [module.weight.detach().to(self.dtype) for module in network.conv
                             if isinstance(module, torch.nn.Conv2d)]
        lstm = network.lstm
        self.input_weight = lstm.weight_ih_l0.detach().to(self.dtype)
        self.bias = (lstm.bias_ih_l0 + lstm.bias_hh_l0).detach().to(self.dtype)
        self.recurrent_weight = lstm.weight_hh_l0.detach()
        self.advantage_weight = network.advantage.weight.detach()
        self.value_weight = network.value.weight.detach()

    def __call__(self, frames: torch.Tensor, state: tuple[torch.Tensor, torch.Tensor]
                 ) -> tuple[torch.Tensor, tuple[torch.Tensor, torch.Tensor]]:
        """frames uint8 (batch, H, W, C), state (h, c) each (1, batch, units) -> Q (batch, actions), new state."""
        height, width = self.used_frame_size
        features = frames[:, :height, :width].to(self.dtype).mul_(1.0 / 255.0).permute(0, 3, 1, 2)
        for weight, (_, _, stride) in zip(self.conv_weights, CONV_LAYERS):
            features = conv_relu(features, weight, stride, self.fused)
        gates = torch.addmm(self.bias, features.flatten(1), self.input_weight.t()).float()
        hidden, cell = state[0][0], state[1][0]
        gates.addmm_(hidden, self.recurrent_weight.t())
        input_gate, forget_gate, candidate, output_gate = gates.chunk(4, dim=1)
        cell = torch.sigmoid(forget_gate) * cell + torch.sigmoid(input_gate) * torch.tanh(candidate)
        hidden = torch.sigmoid(output_gate) * torch.tanh(cell)
        advantage_stream, value_stream = hidden.chunk(2, dim=1)
        advantage = advantage_stream @ self.advantage_weight.t()
        q_values = value_stream @ self.value_weight.t() + advantage - advantage.mean(dim=1, keepdim=True)
        return q_values, (hidden[None], cell[None])


def step_seconds(network: D3RQN, n_slots: int, precision: str, rounds: int = AUTO_TIMING_ROUNDS) -> float:
    """Median CPU seconds of one batched step of n_slots random frames in this precision."""
    batched = BatchedQ(network, n_slots, precision)
    rng = np.random.default_rng(0)
    frames = [rng.integers(0, 256, network.frame_shape, dtype=np.uint8) for _ in range(n_slots)]
    slots = list(range(n_slots))
    batched.q_values(slots, frames)  # first call: allocations, oneDNN's kernel choice
    seconds = []
    for _ in range(rounds):
        started = time.process_time()
        batched.q_values(slots, frames)
        seconds.append(time.process_time() - started)
    return statistics.median(seconds)


def choose_precision(network: D3RQN, n_slots: int, requested: str, option: str = "actor.inference") -> str:
    """The precision to act in: as configured, or for "auto" bfloat16 where it runs and times clearly faster
    here. An explicit bfloat16 this CPU cannot run raises cpu_capability.PrecisionUnavailable."""
    if requested not in INFERENCE_PRECISIONS:
        raise ValueError(f"inference precision must be one of {', '.join(INFERENCE_PRECISIONS)}, got {requested!r}")
    if requested != "auto":
        cpu_capability.require_precision(option, requested)
        return requested
    problem = cpu_capability.bfloat16_problem()
    if problem is not None:
        log.info("%s auto: float32, since bfloat16 cannot run here (%s)", option, problem)
        return "float32"
    float32_s, bfloat16_s = (step_seconds(network, n_slots, precision) for precision in ("float32", "bfloat16"))
    chosen = "bfloat16" if float32_s > AUTO_MIN_SPEEDUP * bfloat16_s else "float32"
    log.info("inference %s: a step of %d simulators took %.2f ms in float32 and %.2f ms in bfloat16 (CPU time)",
             chosen, n_slots, 1e3 * float32_s, 1e3 * bfloat16_s)
    return chosen
