"""Floating-point operations of one learner update, counted from the network's shapes.

Counted: the multiply-adds of the convolutions and of the matrix products (the
LSTM's input projection and recurrence, the dueling head), two FLOPs each, in
the forward and the backward passes. Not counted: elementwise work (ReLU,
gates, scaling, the loss), Adam and the soft target update, which are memory
passes, not arithmetic. The recurrence counts every step's product with the
previous hidden state, the first one (a zero state) included, as nn.LSTM
computes it.

One update (learner/update.py) is: the online network forward over the
B x (T + 1) frames s_0..s_T, the target network forward over the same frames,
and the online backward pass. The backward pass needs the gradient of the
weights of every layer and of the inputs of every layer but the first (the
frames need no gradient), over the frames s_0..s_T-1 only: s_T's online
Q-values enter the loss detached. `backward_steps=T + 1` counts what a plain
autograd pass over all T + 1 frames computes (learner.loss.one_pass_loss).
"""

from __future__ import annotations

from common.config import LearnerConfig, NetworkConfig
from common.network import CONV_LAYERS


def conv_multiply_adds(network: NetworkConfig) -> list[int]:
    """Multiply-adds per frame of each convolution, first layer first."""
    height, width, channels = network.frame_height, network.frame_width, network.frame_channels
    counts = []
    for filters, kernel, stride in CONV_LAYERS:
        height = (height - kernel) // stride + 1
        width = (width - kernel) // stride + 1
        counts.append(height * width * filters * channels * kernel * kernel)
        channels = filters
    return counts


def conv_features(network: NetworkConfig) -> int:
    height, width = network.frame_height, network.frame_width
    for _, kernel, stride in CONV_LAYERS:
        height = (height - kernel) // stride + 1
        width = (width - kernel) // stride + 1
    return CONV_LAYERS[-1][0] * height * width


def forward_flops(network: NetworkConfig, traces: int, steps: int) -> dict[str, float]:
    """FLOPs of one forward pass over `traces` traces of `steps` frames, by part."""
    frames = traces * steps
    units = network.lstm_units
    return {
        "conv": 2.0 * frames * sum(conv_multiply_adds(network)),
        "lstm input projection": 2.0 * frames * conv_features(network) * 4 * units,
        "lstm recurrence": 2.0 * frames * units * 4 * units,
        "dueling head": 2.0 * frames * (units // 2) * (network.n_actions + 1),
    }


def backward_flops(network: NetworkConfig, traces: int, steps: int) -> dict[str, float]:
    """FLOPs of the backward pass over `steps` frames per trace: the gradients of the weights and of
    every input but the frames and the zero initial state."""
    frames = traces * steps
    forward = forward_flops(network, traces, steps)
    first_layer = 2.0 * frames * conv_multiply_adds(network)[0]
    initial_state = 2.0 * traces * network.lstm_units * 4 * network.lstm_units
    return {
        "conv": 2.0 * forward["conv"] - first_layer,
        "lstm input projection": 2.0 * forward["lstm input projection"],
        "lstm recurrence": 2.0 * forward["lstm recurrence"] - initial_state,
        "dueling head": 2.0 * forward["dueling head"],
    }


def update_flops(network: NetworkConfig, learner: LearnerConfig, backward_steps: int | None = None,
                 with_q_after: bool = False) -> dict[str, float]:
    """FLOPs of one update by phase; `backward_steps` defaults to what the update needs: T, or T - burn_in
    from a stored state (learner.stored_state: the burn-in steps run forward only)."""
    traces, steps = learner.batch_size, learner.trace_length + 1
    if backward_steps is None:
        backward_steps = learner.trace_length - (learner.burn_in if learner.stored_state else 0)
    online = forward_flops(network, traces, steps)
    backward = backward_flops(network, traces, backward_steps)
    phases = {
        "online forward: conv": online["conv"],
        "online forward: lstm + head": online["lstm input projection"] + online["lstm recurrence"] + online["dueling head"],
        "target forward": sum(online.values()),
        "backward: conv": backward["conv"],
        "backward: lstm + head": backward["lstm input projection"] + backward["lstm recurrence"] + backward["dueling head"],
    }
    if with_q_after:
        phases["VDBE after-pass"] = sum(forward_flops(network, traces, learner.trace_length).values())
    return phases
