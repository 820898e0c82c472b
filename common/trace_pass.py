"""The learner's trace pass: the hand-written forward and backward passes D3RQN.trace_q_values runs.

D3RQN.forward serves every caller; the learner's update instead runs
D3RQN.trace_q_values, which computes the same Q-values (equal within
floating-point rounding, tests/test_network.py) with less work on the CPU:

- frames are scaled to [0, 1] once per batch (scale_frames), time-major, and
  the online and target networks share them; only the 60x196 of a 66x200
  frame that the VALID convolutions read are kept;
- each convolution runs with its ReLU fused (oneDNN post-op), and the three
  layers' backward is written out by hand (ConvStack);
- the LSTM's input projection is one GEMM over all frames (Projection) and
  the recurrence a hand-written loop with a hand-written backward
  (Recurrence): the weight gradients are one GEMM each over all steps, the
  first step (zero state) needs no recurrent product, and the recurrent
  product is computed as (W_hh h^T)^T, which MKL runs twice as fast at batch
  10 as h W_hh^T;
- frames past `grad_steps` (the learner's s_T, whose Q-values only enter
  detached) go through the forward pass but not through the backward pass.

Each choice measured faster, one thread, on the project's 2-core Xeon with
torch 2.13; deploy/bench/learner_speed.py times the whole against autograd's,
and the learner picks between the two by timing both (learner/update.py).
"""

from __future__ import annotations

import torch

# (filters, kernel, stride) of the network's three VALID, bias-free convolutions (common/network.py).
CONV_LAYERS = ((32, 8, 4), (64, 4, 2), (64, 3, 1))


def scale_frames(frames: torch.Tensor, size: tuple[int, int] | None = None,
                 out: torch.Tensor | None = None) -> torch.Tensor:
    """uint8 frames (B, T, H, W, C) -> float pixels in [0, 1], (T * B, C, h, w), time-major, channels-last.

    `size` (h, w) keeps only the top-left part of each frame (D3RQN.used_frame_size:
    what the convolutions read); default, all of it. The values are bit-identical
    to D3RQN.forward's ``frames.float().mul_(1 / 255)``. `out`, if given, is a
    float32 (T * B, h, w, C) buffer to write into.
    """
    batch, time, height, width, channels = frames.shape
    height, width = size if size is not None else (height, width)
    if out is None:
        out = torch.empty((time * batch, height, width, channels), dtype=torch.float32, device=frames.device)
    # A copy, then an in-place scaling: two vectorised passes, twice as fast as one mul(uint8, float, out=).
    source = frames[:, :, :height, :width].transpose(0, 1)
    out.view(time, batch, height, width, channels).copy_(source).mul_(1.0 / 255.0)
    return out.permute(0, 3, 1, 2)


def fused_relu_convolution_available(device: torch.device) -> bool:
    return (device.type == "cpu" and torch.backends.mkldnn.is_available()
            and hasattr(torch.ops.mkldnn, "_convolution_pointwise"))


def conv_relu(pixels: torch.Tensor, weight: torch.Tensor, stride: int, fused: bool) -> torch.Tensor:
    if fused:
        return torch.ops.mkldnn._convolution_pointwise(pixels, weight, None, [0, 0], [stride, stride], [1, 1], 1,
                                                       "relu", [], "")
    return torch.relu_(torch.nn.functional.conv2d(pixels, weight, stride=stride))


class ConvStack(torch.autograd.Function):
    """The three convolutions with ReLU, flattened to (N, features) in (C, H, W) order.

    The backward pass runs over the first `grad_rows` frames only: the caller
    promises that the gradient of the other rows is zero (checked).
    """

    @staticmethod
    def forward(ctx, pixels, grad_rows, fused, *weights):
        activations = [pixels]
        for weight, (_, _, stride) in zip(weights, CONV_LAYERS):
            activations.append(conv_relu(activations[-1], weight, stride, fused))
        ctx.save_for_backward(*activations, *weights)
        ctx.grad_rows = grad_rows
        return activations[-1].flatten(1)

    @staticmethod
    def backward(ctx, grad_features):
        saved = ctx.saved_tensors
        layers = len(CONV_LAYERS)
        activations, weights = saved[:layers + 1], saved[layers + 1:]
        rows = ctx.grad_rows
        _check_zero_beyond(grad_features, rows)
        grad = grad_features[:rows].view(activations[-1][:rows].shape).contiguous(memory_format=torch.channels_last)
        weight_grads = [None] * layers
        for layer in reversed(range(layers)):
            grad = torch.ops.aten.threshold_backward(grad, activations[layer + 1][:rows], 0)
            stride = CONV_LAYERS[layer][2]
            needs_input = layer > 0 or ctx.needs_input_grad[0]
            grad_input, weight_grads[layer], _ = torch.ops.aten.convolution_backward(
                grad, activations[layer][:rows], weights[layer], None, [stride, stride], [0, 0], [1, 1],
                False, [0, 0], 1, [needs_input, ctx.needs_input_grad[3 + layer], False])
            grad = grad_input
        grad_pixels = None
        if ctx.needs_input_grad[0]:
            grad_pixels = torch.zeros_like(activations[0])
            grad_pixels[:rows] = grad
        return (grad_pixels, None, None, *weight_grads)


class Projection(torch.autograd.Function):
    """features @ weight^T + bias as one GEMM; the backward over the first `grad_rows` rows only."""

    @staticmethod
    def forward(ctx, features, weight, bias, grad_rows):
        ctx.save_for_backward(features, weight)
        ctx.grad_rows = grad_rows
        return torch.addmm(bias, features, weight.t())

    @staticmethod
    def backward(ctx, grad):
        features, weight = ctx.saved_tensors
        rows = ctx.grad_rows
        _check_zero_beyond(grad, rows)
        grad = grad[:rows]
        grad_features = grad_weight = grad_bias = None
        if ctx.needs_input_grad[0]:
            grad_features = features.new_empty(features.shape)
            torch.mm(grad, weight, out=grad_features[:rows])
            grad_features[rows:].zero_()
        if ctx.needs_input_grad[1]:
            grad_weight = grad.t().mm(features[:rows])
        if ctx.needs_input_grad[2]:
            grad_bias = grad.sum(0)
        return grad_features, grad_weight, grad_bias, None


def lstm_steps(projected: torch.Tensor, weight_hh: torch.Tensor,
               state: tuple[torch.Tensor, torch.Tensor] | None = None
               ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """The LSTM recurrence over projected inputs (steps, B, 4H) from `state` (h, c), each (B, H), or from zero;
    PyTorch's gate order i, f, g, o. Returns the gates after their nonlinearities (steps, B, 4, H), the cells,
    their tanh and the hidden states, each (steps, B, H)."""
    steps, batch, four_units = projected.shape
    units = four_units // 4
    gates = projected.new_empty(steps, batch, 4, units)
    cells = projected.new_empty(steps, batch, units)
    tanh_cells = projected.new_empty(steps, batch, units)
    hidden = projected.new_empty(steps, batch, units)
    for t in range(steps):
        step = gates[t]
        previous = hidden[t - 1] if t else (None if state is None else state[0])
        if previous is None:  # the zero state: no recurrent product
            step.view(batch, four_units).copy_(projected[0])
        else:
            # (W_hh h^T)^T: MKL runs this twice as fast at batch 10 as h W_hh^T, nn.LSTM's order.
            recurrent = torch.mm(weight_hh, previous.t())
            torch.add(projected[t], recurrent.t(), out=step.view(batch, four_units))
        step[:, :2].sigmoid_()
        step[:, 2].tanh_()
        step[:, 3].sigmoid_()
        input_gate, forget_gate, candidate, output_gate = step.unbind(1)
        previous_cell = cells[t - 1] if t else (None if state is None else state[1])
        if previous_cell is None:
            torch.mul(input_gate, candidate, out=cells[0])
        else:
            torch.mul(forget_gate, previous_cell, out=cells[t]).addcmul_(input_gate, candidate)
        torch.tanh(cells[t], out=tanh_cells[t])
        torch.mul(output_gate, tanh_cells[t], out=hidden[t])
    return gates, cells, tanh_cells, hidden


class Recurrence(torch.autograd.Function):
    """lstm_steps under autograd: returns the hidden states (steps, B, H). The backward pass (through time,
    by hand) covers the first `grad_steps` steps; the caller promises that no gradient reaches the later
    ones (checked). The initial state, if any, is data: no gradient flows to it.
    """

    @staticmethod
    def forward(ctx, projected, weight_hh, grad_steps, state=None):
        gates, cells, tanh_cells, hidden = lstm_steps(projected, weight_hh, state)
        ctx.save_for_backward(gates, cells, tanh_cells, hidden, weight_hh)
        ctx.grad_steps = grad_steps
        ctx.initial = state
        return hidden

    @staticmethod
    def backward(ctx, grad_hidden):
        gates, cells, tanh_cells, hidden, weight_hh = ctx.saved_tensors
        steps, batch, _, units = gates.shape
        n = ctx.grad_steps
        _check_zero_beyond(grad_hidden, n)
        input_gate, forget_gate, candidate, output_gate = gates[:n].unbind(2)
        initial = ctx.initial
        first_cell = torch.zeros_like(cells[:1]) if initial is None else initial[1][None]
        previous_cells = torch.cat([first_cell, cells[:n - 1]])
        # Factors that do not depend on the recursion, for all steps at once:
        # dc_t += dh_t * o_t * (1 - tanh(c_t)^2); d(pre i, f, g) = dc_t * factors; d(pre o) = dh_t * factor.
        through_tanh = output_gate * (1.0 - tanh_cells[:n] * tanh_cells[:n])
        cell_factors = torch.stack([candidate * input_gate * (1.0 - input_gate),
                                    previous_cells * forget_gate * (1.0 - forget_gate),
                                    input_gate * (1.0 - candidate * candidate)], dim=2)
        output_factor = tanh_cells[:n] * output_gate * (1.0 - output_gate)
        grad_projected = gates.new_empty(steps, batch, 4, units)
        grad_projected[n:].zero_()
        grad_gates = grad_projected[:n]
        grad_h = grad_hidden[n - 1]
        grad_c = grad_h * through_tanh[n - 1]
        for t in reversed(range(n)):
            if t < n - 1:
                grad_h = torch.addmm(grad_hidden[t], grad_gates[t + 1].view(batch, 4 * units), weight_hh)
                grad_c = grad_c.mul_(forget_gate[t + 1]).addcmul_(grad_h, through_tanh[t])
            torch.mul(grad_c.unsqueeze(1), cell_factors[t], out=grad_gates[t, :, :3])
            torch.mul(grad_h, output_factor[t], out=grad_gates[t, :, 3])
        grad_weight_hh = None
        if ctx.needs_input_grad[1]:
            flat = grad_gates.view(n * batch, 4 * units)
            grad_weight_hh = flat[batch:].t().mm(hidden[:n - 1].reshape((n - 1) * batch, units))
            if initial is not None:
                grad_weight_hh.addmm_(flat[:batch].t(), initial[0])
        return grad_projected.view(steps, batch, 4 * units), grad_weight_hh, None, None


def _check_zero_beyond(grad: torch.Tensor, rows: int) -> None:
    if rows < grad.shape[0] and bool(grad[rows:].any()):
        raise RuntimeError("a gradient reached frames the trace pass was told carry none (grad_steps)")
