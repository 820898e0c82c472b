import numpy as np
import pytest
import torch

import common.network as network_module
from common.config import NetworkConfig
from common.config_values import load_config
from common.network import (
    D3RQN, conv_input_extent, conv_output_shape, load_numpy_weights, resolve_device, weights_to_numpy,
)
from common.trace_pass import scale_frames
from common.schema.fields import ConfigError

TINY = NetworkConfig(frame_height=36, frame_width=40, lstm_units=8, n_actions=5)


def make_net(config: NetworkConfig = TINY, seed: int = 0) -> D3RQN:
    torch.manual_seed(seed)
    return D3RQN(config).eval()


def random_frames(config: NetworkConfig, batch: int, time: int, seed: int = 0) -> torch.Tensor:
    generator = torch.Generator().manual_seed(seed)
    shape = (batch, time, config.frame_height, config.frame_width, config.frame_channels)
    return torch.randint(0, 256, shape, dtype=torch.uint8, generator=generator)


def test_paper_sizes_give_5376_features_and_the_expected_shapes():
    config = NetworkConfig()
    # 66x200 -> (66-8)//4+1 = 15, (200-8)//4+1 = 49 -> (15-4)//2+1 = 6, (49-4)//2+1 = 23 -> 4, 21
    assert conv_output_shape(66, 200) == (4, 21)
    net = make_net(config)
    assert net.n_features == 64 * 4 * 21 == 5376
    assert net.lstm.input_size == 5376 and net.lstm.hidden_size == 512
    assert net.advantage.in_features == net.value.in_features == 256
    assert net.advantage.out_features == 5 and net.value.out_features == 1
    with torch.no_grad():
        q_values, (h, c) = net(random_frames(config, batch=2, time=3))
    assert q_values.shape == (2, 3, 5)
    assert h.shape == c.shape == (1, 2, 512)


def test_no_biases_in_convolutions_and_dueling_streams():
    net = make_net()
    convolutions = [m for m in net.modules() if isinstance(m, torch.nn.Conv2d)]
    assert [(m.out_channels, m.kernel_size, m.stride) for m in convolutions] == [
        (32, (8, 8), (4, 4)), (64, (4, 4), (2, 2)), (64, (3, 3), (1, 1))]
    assert all(m.bias is None for m in convolutions)
    assert net.advantage.bias is None and net.value.bias is None


def test_one_frame_at_a_time_matches_the_whole_trace():
    net = make_net(seed=3)
    frames = random_frames(TINY, batch=3, time=6, seed=1)
    with torch.no_grad():
        whole, whole_state = net(frames)
        state = net.initial_state(3)
        steps = []
        for t in range(frames.shape[1]):
            q_values, state = net(frames[:, t:t + 1], state)
            steps.append(q_values)
    torch.testing.assert_close(torch.cat(steps, dim=1), whole, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(state, whole_state, rtol=1e-5, atol=1e-6)


def test_the_state_carries_history():
    net = make_net(seed=3)
    frames = random_frames(TINY, batch=1, time=4, seed=2)
    with torch.no_grad():
        q_with_history = net(frames)[0][:, -1]
        q_from_zero = net(frames[:, -1:])[0][:, -1]
    assert not torch.allclose(q_with_history, q_from_zero)


def test_dueling_head_removes_the_mean_advantage():
    net = make_net(seed=4)
    captured = {}
    net.advantage.register_forward_hook(lambda module, args, out: captured.__setitem__("a", out))
    net.value.register_forward_hook(lambda module, args, out: captured.__setitem__("v", out))
    with torch.no_grad():
        q_values, _ = net(random_frames(TINY, batch=2, time=3, seed=5))
    advantage, value = captured["a"], captured["v"]
    assert advantage.shape == (2, 3, 5) and value.shape == (2, 3, 1)
    # Q = V + A - mean_a A, so mean_a Q = V and Q - V = A - mean_a A.
    torch.testing.assert_close(q_values.mean(dim=-1, keepdim=True), value, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(q_values - value, advantage - advantage.mean(dim=-1, keepdim=True))
    assert advantage.mean(dim=-1).abs().max() > 1e-4  # the identity is not trivially met by A's mean being 0


def test_dueling_streams_use_the_two_halves_of_the_lstm_output():
    net = make_net(seed=6)
    inputs = {}
    net.advantage.register_forward_hook(lambda module, args, out: inputs.__setitem__("a", args[0]))
    net.value.register_forward_hook(lambda module, args, out: inputs.__setitem__("v", args[0]))
    net.lstm.register_forward_hook(lambda module, args, out: inputs.__setitem__("lstm", out[0]))
    with torch.no_grad():
        net(random_frames(TINY, batch=2, time=3, seed=7))
    lstm_out = inputs["lstm"].transpose(0, 1)  # the LSTM runs time-major
    torch.testing.assert_close(inputs["a"], lstm_out[..., :4])
    torch.testing.assert_close(inputs["v"], lstm_out[..., 4:])


def test_uint8_frames_are_scaled_to_unit_range_inside_the_model():
    net = make_net()
    seen = {}
    net.conv.register_forward_pre_hook(lambda module, args: seen.__setitem__("pixels", args[0]))
    frames = random_frames(TINY, batch=2, time=2, seed=8)
    frames[0, 0, 0, 0, 0] = 255
    frames[0, 0, 0, 0, 1] = 0
    with torch.no_grad():
        net(frames)
    pixels = seen["pixels"]
    assert pixels.dtype == torch.float32 and pixels.shape == (4, 3, 36, 40)
    expected = frames.reshape(4, 36, 40, 3).permute(0, 3, 1, 2).double() / 255.0
    torch.testing.assert_close(pixels.double(), expected, rtol=0, atol=1e-7)
    assert pixels.max() == 1.0 and pixels.min() == 0.0


@pytest.mark.parametrize("frames", [
    torch.zeros(1, 2, 36, 40, 3),  # float, not uint8
    torch.zeros(1, 2, 40, 36, 3, dtype=torch.uint8),  # height and width swapped
    torch.zeros(2, 36, 40, 3, dtype=torch.uint8),  # no time axis
])
def test_wrong_frames_are_a_value_error(frames):
    with pytest.raises(ValueError, match="frames must be"):
        make_net()(frames)


def test_initial_state_is_zero():
    h, c = make_net().initial_state(4)
    assert h.shape == c.shape == (1, 4, 8)
    assert not h.any() and not c.any()


def test_resolve_device():
    assert resolve_device(NetworkConfig(device="cpu")) == torch.device("cpu")
    expected = "cuda" if torch.cuda.is_available() else "cpu"
    assert resolve_device(NetworkConfig(device="auto")).type == expected


def test_frames_smaller_than_the_convolutions_are_a_config_error():
    with pytest.raises(ConfigError, match="network.frame_height"):
        load_config("paper", overrides={"network.frame_height": 35})


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_runs_on_cuda_like_on_cpu():
    net = make_net()
    frames = random_frames(TINY, batch=2, time=3)
    with torch.no_grad(), torch.backends.cudnn.flags(enabled=True, allow_tf32=False):  # TF32 rounds to 10 bits
        on_cpu = net(frames)[0]
        on_cuda = net.to("cuda")(frames.to("cuda"))[0]
    torch.testing.assert_close(on_cuda.cpu(), on_cpu, rtol=1e-4, atol=1e-5)


# --- numpy weights for the wire --------------------------------------------------

def test_numpy_weights_round_trip():
    source, destination = make_net(seed=1), make_net(seed=2)
    tensors = weights_to_numpy(source)
    assert set(tensors) == set(source.state_dict())
    assert all(isinstance(array, np.ndarray) for array in tensors.values())
    load_numpy_weights(destination, tensors)
    frames = random_frames(TINY, batch=2, time=3)
    with torch.no_grad():
        torch.testing.assert_close(destination(frames)[0], source(frames)[0], rtol=0, atol=0)


def test_numpy_weights_are_copies():
    net = make_net()
    tensors = weights_to_numpy(net)
    tensors["advantage.weight"][:] = 0.0
    assert net.advantage.weight.abs().sum() > 0


def test_loading_mismatched_weights_is_a_value_error_and_changes_nothing():
    net = make_net(seed=1)
    before = weights_to_numpy(net)
    good = weights_to_numpy(make_net(seed=2))
    missing = {k: v for k, v in good.items() if k != "value.weight"}
    extra = {**good, "head.weight": np.zeros(3, np.float32)}
    wrong_shape = {**good, "value.weight": np.zeros((1, 5), np.float32)}
    not_finite = {**good, "value.weight": np.full((1, 4), np.nan, np.float32)}
    integers = {**good, "value.weight": np.zeros((1, 4), np.int64)}
    for tensors, message in ((missing, r"missing \['value.weight'\]"), (extra, r"unexpected \['head.weight'\]"),
                             (wrong_shape, r"'value.weight': shape \(1, 5\)"), (not_finite, "NaN"),
                             (integers, "not floating point")):
        with pytest.raises(ValueError, match=message):
            load_numpy_weights(net, tensors)
    after = weights_to_numpy(net)
    assert all(np.array_equal(before[k], after[k]) for k in before)


# --- the learner's trace pass (D3RQN.trace_q_values) -------------------------------

def lively_net(config: NetworkConfig = TINY, seed: int = 3) -> D3RQN:
    """A network whose LSTM gates are far from their resting values, so that a wrong gate shows."""
    net = make_net(config, seed)
    with torch.no_grad():
        for parameter in net.lstm.parameters():
            parameter.mul_(3.0)
    return net


def test_scale_frames_is_time_major_channels_last_and_bit_identical():
    frames = random_frames(TINY, batch=3, time=4, seed=9)
    pixels = scale_frames(frames)
    assert pixels.shape == (12, 3, 36, 40) and pixels.is_contiguous(memory_format=torch.channels_last)
    expected = frames.transpose(0, 1).reshape(12, 36, 40, 3).permute(0, 3, 1, 2).float().mul_(1.0 / 255.0)
    assert torch.equal(pixels, expected)  # the same rounding as forward()'s scaling
    cropped = scale_frames(frames, (30, 31))
    assert torch.equal(cropped, expected[:, :, :30, :31])


def test_the_convolutions_read_only_the_top_left_60x196_of_a_paper_frame():
    assert conv_input_extent(66, 200) == (60, 196)
    assert conv_input_extent(36, 40) == (36, 36)
    assert make_net(NetworkConfig()).used_frame_size == (60, 196)


@pytest.mark.parametrize("fused", [True, False], ids=["fused-relu", "plain-conv"])
@pytest.mark.parametrize("config", [TINY, NetworkConfig(frame_height=44, frame_width=50, lstm_units=12)],
                         ids=["tiny", "cropped"])
def test_trace_q_values_equal_forward(config, fused, monkeypatch):
    monkeypatch.setattr(network_module, "fused_relu_convolution_available", lambda device: fused)
    net = lively_net(config)
    frames = random_frames(config, batch=4, time=6, seed=10)
    with torch.no_grad():
        expected, _ = net(frames)
        for size in (None, net.used_frame_size):
            q_values = net.trace_q_values(scale_frames(frames, size), batch=4)
            torch.testing.assert_close(q_values, expected, rtol=1e-5, atol=1e-6)
    q_values = net.trace_q_values(scale_frames(frames, net.used_frame_size), batch=4)  # with autograd on
    torch.testing.assert_close(q_values.detach(), expected, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("fused", [True, False], ids=["fused-relu", "plain-conv"])
def test_trace_gradients_equal_autograd_through_forward(fused, monkeypatch):
    monkeypatch.setattr(network_module, "fused_relu_convolution_available", lambda device: fused)
    net = lively_net()
    frames = random_frames(TINY, batch=4, time=6, seed=11)
    weights = torch.randn(4, 5, 5, generator=torch.Generator().manual_seed(12))  # a loss on steps 0..4 only

    q_values = net.trace_q_values(scale_frames(frames, net.used_frame_size), batch=4, grad_steps=5)
    (q_values[:, :5] * weights).sum().backward()
    trace_gradients = {name: p.grad.clone() for name, p in net.named_parameters()}
    net.zero_grad()
    expected, _ = net(frames)
    (expected[:, :5] * weights).sum().backward()
    for name, parameter in net.named_parameters():
        torch.testing.assert_close(trace_gradients[name], parameter.grad, rtol=1e-4, atol=1e-6, msg=name)
    assert all(g.abs().max() > 0 for g in trace_gradients.values())


def random_state(net: D3RQN, batch: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    generator = torch.Generator().manual_seed(seed)
    hidden = torch.rand(1, batch, net.lstm_units, generator=generator) * 1.6 - 0.8  # h lies in (-1, 1)
    return hidden, torch.randn(1, batch, net.lstm_units, generator=generator) * 2.0


def test_trace_q_values_from_a_stored_state_equal_forward_from_it():
    net = lively_net()
    frames = random_frames(TINY, batch=3, time=5, seed=21)
    state = random_state(net, 3, seed=22)
    with torch.no_grad():
        expected, _ = net(frames, state)
        zero_start, _ = net(frames)
        q_values = net.trace_q_values(scale_frames(frames, net.used_frame_size), batch=3, state=state)
    torch.testing.assert_close(q_values, expected, rtol=1e-5, atol=1e-6)
    assert not torch.allclose(expected, zero_start, atol=1e-3)  # the state matters


@pytest.mark.parametrize("burn_in", [0, 2])
def test_trace_gradients_from_a_stored_state_with_burn_in_equal_autograd(burn_in):
    """R2D2's burn-in: the first burn_in steps run from the stored state without gradient; the rest train.
    The autograd reference: forward() over the burn-in under no_grad, then over the rest from its state."""
    net = lively_net()
    frames = random_frames(TINY, batch=4, time=6, seed=23)
    state = random_state(net, 4, seed=24)
    weights = torch.randn(4, 5, 5, generator=torch.Generator().manual_seed(25))  # a loss on steps 0..4
    weights[:, :burn_in] = 0.0

    q_values = net.trace_q_values(scale_frames(frames, net.used_frame_size), batch=4, grad_steps=5, state=state,
                                  burn_in=burn_in)
    (q_values[:, :5] * weights).sum().backward()
    trace_gradients = {name: p.grad.clone() for name, p in net.named_parameters()}
    net.zero_grad()
    with torch.no_grad():
        burnt, later_state = net(frames[:, :burn_in], state) if burn_in else (None, state)
    rest, _ = net(frames[:, burn_in:], later_state)
    expected = rest if burnt is None else torch.cat([burnt, rest], dim=1)
    torch.testing.assert_close(q_values.detach(), expected.detach(), rtol=1e-5, atol=1e-6)
    (expected[:, :5] * weights).sum().backward()
    for name, parameter in net.named_parameters():
        torch.testing.assert_close(trace_gradients[name], parameter.grad, rtol=1e-4, atol=1e-6, msg=name)
    assert all(g.abs().max() > 0 for g in trace_gradients.values())


def test_burnt_in_steps_carry_no_gradient():
    net = lively_net()
    frames = random_frames(TINY, batch=2, time=4, seed=26)
    q_values = net.trace_q_values(scale_frames(frames), batch=2, state=random_state(net, 2, seed=27), burn_in=2)
    q_values[:, :2].sum().backward()
    assert all(p.grad is None or not p.grad.any() for p in net.parameters())
    with pytest.raises(ValueError, match="burn_in"):
        net.trace_q_values(scale_frames(frames), batch=2, grad_steps=2, burn_in=2)


def test_steps_past_grad_steps_carry_no_gradient():
    net = lively_net()
    frames = random_frames(TINY, batch=2, time=4, seed=13)
    q_values = net.trace_q_values(scale_frames(frames), batch=2, grad_steps=3)
    q_values[:, 3:].sum().backward()
    assert all(p.grad is None or not p.grad.any() for p in net.parameters())


def test_trace_q_values_check_their_arguments():
    net = make_net()
    pixels = scale_frames(random_frames(TINY, batch=2, time=3))
    with pytest.raises(ValueError, match="pixels must be"):
        net.trace_q_values(pixels, batch=4)  # 6 frames are not whole traces of 4
    with pytest.raises(ValueError, match="pixels must be"):
        net.trace_q_values(pixels[:, :, :30], batch=2)
    with pytest.raises(ValueError, match="grad_steps"):
        net.trace_q_values(pixels, batch=2, grad_steps=4)
