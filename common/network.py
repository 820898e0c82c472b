"""The D3RQN: convolutions, an LSTM over the trace, and a dueling head.

Shapes follow docs/method.md ("The network"): frames are uint8 (batch, time,
height, width, channels) and are scaled to [0, 1] inside the model, so replay
and actors only ever hold uint8. The recurrent state is explicit, in and out, as PyTorch's LSTM
holds it: a pair (h, c), each (1, batch, lstm_units). An actor steps one frame
at a time carrying the state; a learner runs whole traces from a zero state, or
(learner.stored_state) from the state an actor stored with the episode.
"""

from __future__ import annotations

import contextlib

import numpy as np
import torch
from torch import nn

from common.config import NetworkConfig
from common.trace_pass import (CONV_LAYERS, ConvStack, Projection, Recurrence, conv_relu,
                               fused_relu_convolution_available, lstm_steps, scale_frames)

RecurrentState = tuple[torch.Tensor, torch.Tensor]


def resolve_device(config: NetworkConfig) -> torch.device:
    """The configured device; "auto" is CUDA when available, else CPU."""
    if config.device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(config.device)


def initial_network(config: NetworkConfig, seed: int) -> "D3RQN":
    """The D3RQN every run starts from, seeded by learner.seed, without touching the caller's RNG: the learner's
    online network, and the network an actor runs before the learner's first weights arrive (the random phase's
    stored states, learner.stored_state), are the same one."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        return D3RQN(config)


def conv_output_shape(height: int, width: int) -> tuple[int, int]:
    """Spatial size after the three VALID convolutions (66x200 -> 4x21)."""
    for _, kernel, stride in CONV_LAYERS:
        height = (height - kernel) // stride + 1
        width = (width - kernel) // stride + 1
    return height, width


def conv_input_extent(height: int, width: int) -> tuple[int, int]:
    """The top-left part of a frame the convolutions read (66x200 -> 60x196): VALID strides leave the rest unused."""
    out_height, out_width = conv_output_shape(height, width)
    for _, kernel, stride in reversed(CONV_LAYERS):
        out_height = (out_height - 1) * stride + kernel
        out_width = (out_width - 1) * stride + kernel
    return out_height, out_width


class D3RQN(nn.Module):
    """Double Dueling Deep Recurrent Q-Network; sizes come from NetworkConfig."""

    def __init__(self, config: NetworkConfig) -> None:
        super().__init__()
        self.frame_shape = (config.frame_height, config.frame_width, config.frame_channels)
        self.lstm_units = config.lstm_units
        self.n_actions = config.n_actions
        layers: list[nn.Module] = []
        in_channels = config.frame_channels
        for filters, kernel, stride in CONV_LAYERS:
            layers += [nn.Conv2d(in_channels, filters, kernel, stride=stride, bias=False), nn.ReLU(inplace=True)]
            in_channels = filters
        self.conv = nn.Sequential(*layers)
        out_height, out_width = conv_output_shape(config.frame_height, config.frame_width)
        self.n_features = in_channels * out_height * out_width
        self.used_frame_size = conv_input_extent(config.frame_height, config.frame_width)
        # Time-major: with batch_first=True, PyTorch's CPU LSTM falls back to a
        # 3x slower batched matmul for the input projection whenever its weights
        # do not require grad (a frozen target network), measured with torch 2.13.
        self.lstm = nn.LSTM(self.n_features, config.lstm_units)
        half = config.lstm_units // 2
        self.advantage = nn.Linear(half, config.n_actions, bias=False)
        self.value = nn.Linear(half, 1, bias=False)
        # The number format of the trace pass's convolutions and LSTM input projection (learner.precision);
        # the weights, the recurrence and the head stay float32.
        self.trace_dtype = torch.float32

    def initial_state(self, batch_size: int, device: torch.device | str | None = None) -> RecurrentState:
        """The zero state every episode and every sampled trace starts from."""
        device = device if device is not None else self.advantage.weight.device
        zeros = torch.zeros(1, batch_size, self.lstm_units, device=device)
        return zeros, zeros.clone()

    def forward(self, frames: torch.Tensor, state: RecurrentState | None = None
                ) -> tuple[torch.Tensor, RecurrentState]:
        """Q-values (batch, time, n_actions) and the state after the last frame."""
        self._check_frames(frames)
        batch, time = frames.shape[:2]
        # NHWC -> NCHW as a view: the result is channels-last in memory, which
        # the CPU (oneDNN) and CUDA convolutions both handle well.
        pixels = frames.reshape(batch * time, *self.frame_shape).permute(0, 3, 1, 2)
        features = self.conv(pixels.float().mul_(1.0 / 255.0)).flatten(1)
        if state is None:
            state = self.initial_state(batch, frames.device)
        time_major = features.reshape(batch, time, self.n_features).transpose(0, 1).contiguous()
        with _native_cpu_lstm():
            outputs, state = self.lstm(time_major, state)
        outputs = outputs.transpose(0, 1)
        advantage_stream, value_stream = outputs.chunk(2, dim=-1)
        advantage = self.advantage(advantage_stream)
        value = self.value(value_stream)
        q_values = value + advantage - advantage.mean(dim=-1, keepdim=True)
        return q_values, state

    def trace_q_values(self, pixels: torch.Tensor, batch: int, grad_steps: int | None = None,
                       state: RecurrentState | None = None, burn_in: int = 0) -> torch.Tensor:
        """Q-values (batch, time, n_actions) of whole traces, as forward() computes them.

        `pixels` comes from scale_frames (time-major; whole frames, or cut to
        used_frame_size, which saves the work on pixels nothing reads). With
        autograd on, the gradient flows through the first `grad_steps` steps only
        (default: all); the Q-values of later steps come detached, and their
        frames are left out of the backward pass. The traces start from `state`
        (h, c), each (1, batch, lstm_units), or from a zero state. With autograd
        on, the first `burn_in` steps run without gradient and hand their state
        on (R2D2's burn-in): their Q-values come detached. Used by the learner
        (learner/update.py); forward() serves the rest.
        """
        frames = pixels.shape[0]
        time = frames // batch
        sizes = {tuple(self.frame_shape[:2]), self.used_frame_size}
        if frames != time * batch or pixels.shape[1] != self.frame_shape[2] or tuple(pixels.shape[2:]) not in sizes:
            raise ValueError(f"pixels must be (time * {batch}, {self.frame_shape[2]}, height, width) with (height, "
                             f"width) one of {sorted(sizes)}, got {tuple(pixels.shape)}")
        grad_steps = time if grad_steps is None else grad_steps
        if not 1 <= grad_steps <= time:
            raise ValueError(f"grad_steps must lie in [1, {time}], got {grad_steps}")
        if not 0 <= burn_in < grad_steps:
            raise ValueError(f"burn_in must lie in [0, grad_steps = {grad_steps}), got {burn_in}")
        if burn_in and torch.is_grad_enabled():
            rows = burn_in * batch
            with torch.no_grad():
                burnt, state = self.trace_head(self.trace_features(pixels[:rows], batch, burn_in), batch, burn_in,
                                               state, final_state=True)
            rest = pixels[rows:]
            steps = grad_steps - burn_in
            return torch.cat([burnt, self.trace_head(self.trace_features(rest, batch, steps), batch, steps, state)], 1)
        return self.trace_head(self.trace_features(pixels, batch, grad_steps), batch, grad_steps, state)

    def trace_features(self, pixels: torch.Tensor, batch: int, grad_steps: int) -> torch.Tensor:
        """trace_q_values' first part: the convolutions, (frames, n_features), in trace_dtype."""
        fused = fused_relu_convolution_available(pixels.device)
        # .to() is differentiable: a bfloat16 pass hands float32 gradients to the float32 weights
        weights = [module.weight.to(self.trace_dtype) for module in self.conv if isinstance(module, nn.Conv2d)]
        pixels = pixels.to(self.trace_dtype)
        if torch.is_grad_enabled():
            return ConvStack.apply(pixels, grad_steps * batch, fused, *weights)
        features = pixels
        for weight, (_, _, stride) in zip(weights, CONV_LAYERS):
            features = conv_relu(features, weight, stride, fused)
        return features.flatten(1)

    def trace_head(self, features: torch.Tensor, batch: int, grad_steps: int, state: RecurrentState | None = None,
                   final_state: bool = False) -> torch.Tensor | tuple[torch.Tensor, RecurrentState]:
        """trace_q_values' second part: the LSTM from `state` (or zero) and the dueling head, (batch, time,
        n_actions); with final_state (autograd off only), also the state after the last step."""
        time = features.shape[0] // batch
        initial = None if state is None else (state[0][0].float(), state[1][0].float())
        lstm = self.lstm
        dtype = features.dtype  # the projection in the features' format, the recurrence in float32
        bias, weight_ih = (lstm.bias_ih_l0 + lstm.bias_hh_l0).to(dtype), lstm.weight_ih_l0.to(dtype)
        if torch.is_grad_enabled():
            projected = Projection.apply(features, weight_ih, bias, grad_steps * batch).float()
            hidden = Recurrence.apply(projected.view(time, batch, -1), lstm.weight_hh_l0, grad_steps, initial)
        else:
            projected = torch.addmm(bias, features, weight_ih.t()).float()
            _, cells, _, hidden = lstm_steps(projected.view(time, batch, -1), lstm.weight_hh_l0, initial)
        advantage_stream, value_stream = hidden.transpose(0, 1).chunk(2, dim=-1)
        advantage = self.advantage(advantage_stream)
        q_values = self.value(value_stream) + advantage - advantage.mean(dim=-1, keepdim=True)
        if grad_steps < time and q_values.requires_grad:
            q_values = torch.cat([q_values[:, :grad_steps], q_values[:, grad_steps:].detach()], dim=1)
        if final_state:
            if torch.is_grad_enabled():
                raise RuntimeError("trace_head hands on its final state only with autograd off")
            return q_values, (hidden[-1:].clone(), cells[-1:].clone())
        return q_values

    def _check_frames(self, frames: torch.Tensor) -> None:
        if frames.dtype != torch.uint8:
            raise ValueError(f"frames must be uint8, got {frames.dtype}")
        if frames.dim() != 5 or tuple(frames.shape[2:]) != self.frame_shape:
            raise ValueError(f"frames must be (batch, time, {', '.join(map(str, self.frame_shape))}), "
                             f"got {tuple(frames.shape)}")


@contextlib.contextmanager
def _native_cpu_lstm():
    """Runs nn.LSTM on PyTorch's own CPU kernels instead of oneDNN's.

    Measured on the 2-core Xeon this project runs on (torch 2.13): the oneDNN
    LSTM takes 3x longer for a training pass over a 10x11 trace and 14x longer
    for one actor step. The switch is global to the process, hence only around
    the LSTM call (convolutions keep oneDNN); it does not affect CUDA (cuDNN).
    """
    enabled = torch.backends.mkldnn.enabled
    torch.backends.mkldnn.enabled = False
    try:
        yield
    finally:
        torch.backends.mkldnn.enabled = enabled


def weights_to_numpy(module: nn.Module) -> dict[str, np.ndarray]:
    """Every tensor of the state dict as a CPU numpy copy, for the Weights message."""
    return {name: tensor.detach().cpu().numpy().copy() for name, tensor in module.state_dict().items()}


def load_numpy_weights(module: nn.Module, tensors: dict[str, np.ndarray]) -> None:
    """Loads a weights_to_numpy() dict; any mismatch is a ValueError naming it, before anything changes."""
    expected = module.state_dict()
    missing = sorted(set(expected) - set(tensors))
    extra = sorted(set(tensors) - set(expected))
    if missing or extra:
        raise ValueError(f"weights do not match the network: missing {missing}, unexpected {extra}")
    converted = {}
    for name, target in expected.items():
        array = np.asarray(tensors[name])
        if array.shape != tuple(target.shape):
            raise ValueError(f"weights {name!r}: shape {array.shape}, the network expects {tuple(target.shape)}")
        if not np.issubdtype(array.dtype, np.floating):
            raise ValueError(f"weights {name!r}: dtype {array.dtype} is not floating point")
        if not np.isfinite(array).all():
            raise ValueError(f"weights {name!r}: contains NaN or infinity")
        converted[name] = torch.tensor(array, dtype=target.dtype)  # a copy: wire arrays are read-only views
    module.load_state_dict(converted)
