"""The D3RQN: convolutions, an LSTM over the trace, and a dueling head.

Shapes follow REFERENCE.md: frames are uint8 (batch, time, height, width,
channels) and are scaled to [0, 1] inside the model, so replay and actors only
ever hold uint8. The recurrent state is explicit, in and out, as PyTorch's LSTM
holds it: a pair (h, c), each (1, batch, lstm_units). An actor steps one frame
at a time carrying the state; a learner runs whole traces from a zero state.
"""

from __future__ import annotations

import contextlib

import numpy as np
import torch
from torch import nn

from common.config import NetworkConfig

# (filters, kernel, stride) of the three VALID, bias-free convolutions.
CONV_LAYERS = ((32, 8, 4), (64, 4, 2), (64, 3, 1))

RecurrentState = tuple[torch.Tensor, torch.Tensor]


def resolve_device(config: NetworkConfig) -> torch.device:
    """The configured device; "auto" is CUDA when available, else CPU."""
    if config.device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(config.device)


def conv_output_shape(height: int, width: int) -> tuple[int, int]:
    """Spatial size after the three VALID convolutions (66x200 -> 4x21)."""
    for _, kernel, stride in CONV_LAYERS:
        height = (height - kernel) // stride + 1
        width = (width - kernel) // stride + 1
    return height, width


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
        # Time-major: with batch_first=True, PyTorch's CPU LSTM falls back to a
        # 3x slower batched matmul for the input projection whenever its weights
        # do not require grad (a frozen target network), measured with torch 2.13.
        self.lstm = nn.LSTM(self.n_features, config.lstm_units)
        half = config.lstm_units // 2
        self.advantage = nn.Linear(half, config.n_actions, bias=False)
        self.value = nn.Linear(half, 1, bias=False)

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
