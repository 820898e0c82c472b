"""Shadow policies (beyond the paper): the target network and a moving average of the online weights, kept
beside the online policy without changing what the actors or the loss see."""

import logging

import numpy as np
import pytest
import torch

from common.checkpoint import CheckpointError, KeptPolicy
from common.run_dir import RunDir
from learner.service import LearnerService
from learner.weight_average import WeightAverage
from tests.test_learner_resume import batches, config, train  # noqa: F401 (config: a fixture)


def shadowed(config, horizon=2, keep_target=True, keep_every=1, shadows_from=0) -> LearnerService:
    config.learner.keep_target, config.learner.ema_updates = keep_target, horizon
    config.learner.keep_every, config.learner.keep_shadows_from = keep_every, shadows_from
    service = LearnerService(config)
    service.start_updates()
    return service


def online(service: LearnerService) -> dict[str, torch.Tensor]:
    return {name: tensor.clone() for name, tensor in service.learner.online.state_dict().items()}


@pytest.mark.parametrize("stride, factors", [
    (1, [27 / 64, 9 / 64, 12 / 64, 16 / 64]),  # a_0 = w0, a_k = a_k-1 + (w_k - a_k-1) / 4
    (2, [9 / 16, 0, 7 / 16, 0]),  # a step at update 2 only, as far as two: 1 - (3/4)^2 = 7/16
    (3, [27 / 64, 0, 0, 37 / 64]),  # at update 3: 1 - (3/4)^3
])
def test_the_moving_average_is_the_hand_computed_one(stride, factors):
    network = torch.nn.Linear(2, 1)
    values = [torch.tensor([[1.0, -2.0]]), torch.tensor([[3.0, 0.5]]), torch.tensor([[-1.0, 4.0]]),
              torch.tensor([[2.0, 2.0]])]  # w0 (the initial weights), then after updates 1, 2, 3
    with torch.no_grad():
        network.weight.copy_(values[0])
    average = WeightAverage(network, horizon=4, stride=stride)
    for updates, weights in enumerate(values[1:], 1):
        with torch.no_grad():
            network.weight.copy_(weights)
        average.update(network, updates)
    by_hand = sum(factor * weights.double() for factor, weights in zip(factors, values))
    assert torch.allclose(average.state_dict()["weight"].double(), by_hand, rtol=0, atol=1e-6)
    assert average.state_dict()["weight"].dtype == torch.float32


def test_the_learners_average_steps_every_ten_updates(config):
    process = shadowed(config, horizon=4)
    history = {0: online(process)}
    for updates, batch in enumerate(batches(20), 1):
        train(process, batch)
        history[updates] = online(process)
    rate = 1 - 0.75 ** 10
    average = process.learner.average.state_dict()
    assert set(average) == set(history[0])
    for name in history[0]:
        by_hand = history[0][name].double()
        for updates in (10, 20):
            by_hand = by_hand + rate * (history[updates][name].double() - by_hand)
        assert torch.allclose(average[name].double(), by_hand, rtol=0, atol=1e-6), name
    assert not all(torch.equal(average[name], history[20][name]) for name in average)  # not the online weights


def test_a_horizon_of_one_is_the_online_weights():
    network = torch.nn.Linear(3, 2)
    average = WeightAverage(network, 1)
    with torch.no_grad():
        network.weight.add_(1.0)
    average.update(network, 10)
    assert torch.equal(average.state_dict()["weight"], network.weight)
    with torch.no_grad():
        network.weight.add_(1.0)
    average.update(network, 11)  # off the stride: no step
    assert not torch.equal(average.state_dict()["weight"], network.weight)
    with pytest.raises(ValueError, match="at least 1"):
        WeightAverage(network, 0)


def test_the_kept_shadows_are_the_target_network_and_the_average(config):
    process = shadowed(config)
    for batch in batches(2):
        train(process, batch)
    process.keep_policy()
    process.keeper.wait()
    run = RunDir.of(config)
    target = KeptPolicy.load(run.policy(2, "target"))
    ema = KeptPolicy.load(run.policy(2, "ema"))
    kept_online = KeptPolicy.load(run.policy(2))
    assert (target.kind, ema.kind, kept_online.kind) == ("target", "ema", "online")
    for name, tensor in process.learner.target.state_dict().items():
        assert torch.equal(target.online[name], tensor), name
        assert torch.equal(ema.online[name], process.learner.average.tensors[name]), name
        assert torch.equal(kept_online.online[name], process.learner.online.state_dict()[name]), name
    assert not torch.equal(target.online[name], kept_online.online[name])  # three different networks
    for shadow in (target, ema):  # the same metadata as the online policy's
        assert (shadow.updates, shadow.env_steps, shadow.wall_s, shadow.cpu, shadow.config) == (
            kept_online.updates, kept_online.env_steps, kept_online.wall_s, kept_online.cpu, kept_online.config)
    assert run.kept_policies() == [(2, run.policy(2))]  # the online curve reads the online policies only
    assert RunDir.of_checkpoint(run.policy(2, "ema")) == run


def test_shadows_are_kept_from_keep_shadows_from_only(config):
    process = shadowed(config, shadows_from=2)
    for batch in batches(3):
        train(process, batch)
        process.keep_policy_if_due()
    process.keeper.wait()
    run = RunDir.of(config)
    assert [updates for updates, _ in run.kept_policies()] == [1, 2, 3]
    assert [updates for updates, _ in run.kept_policies("target")] == [2, 3]
    assert [updates for updates, _ in run.kept_policies("ema")] == [2, 3]


def test_with_shadows_on_training_is_unchanged(config):
    """The same seed and batches give the same losses and online weights, bit for bit, with shadows kept
    every update or with none: the actors act on the online weights, so their actions are the same too."""
    data = batches(4)
    plain = LearnerService(config)
    plain.start_updates()
    for batch in data:
        train(plain, batch)
    process = shadowed(config)
    for batch in data:
        train(process, batch)
        process.keep_policy_if_due()
    process.keeper.wait()
    assert process.updates == plain.updates == 4
    for name, tensor in plain.learner.online.state_dict().items():
        assert torch.equal(tensor, process.learner.online.state_dict()[name]), name
    for name, tensor in plain.learner.target.state_dict().items():
        assert torch.equal(tensor, process.learner.target.state_dict()[name]), name
    plain_weights, weights = plain.learner.online_weights(), process.learner.online_weights()
    assert all(np.array_equal(plain_weights[name], weights[name]) for name in plain_weights)


def test_the_checkpoint_holds_the_average_and_resume_restores_it(config, caplog):
    process = shadowed(config, horizon=3)
    data = batches(13)
    for batch in data[:7]:  # a step at 10 updates, past the resume, and one in step at 0-10 before it
        train(process, batch)
    process.checkpoint()
    resumed = LearnerService(config)
    resumed.resume()
    for name, tensor in process.learner.average.tensors.items():
        assert torch.equal(resumed.learner.average.tensors[name], tensor), name
    for batch in data[7:]:
        train(process, batch)
        train(resumed, batch)
    assert process.updates == 13
    for name, tensor in process.learner.average.tensors.items():
        assert torch.equal(resumed.learner.average.tensors[name], tensor), name

    config.learner.ema_updates = 0  # a run checkpointed without the average, resumed with it on
    LearnerService(config).checkpoint()
    config.learner.ema_updates = 3
    caplog.set_level(logging.WARNING, logger="learner.update")
    late = LearnerService(config)
    late.resume()
    assert any("holds no moving average" in record.message for record in caplog.records)
    for name, tensor in late.learner.online.state_dict().items():
        assert torch.equal(late.learner.average.tensors[name], tensor), name


def test_a_policy_kind_is_checked_and_an_old_file_reads_as_online(tmp_path):
    policy = KeptPolicy(updates=3, env_steps=9, wall_s=1.0, cpu="Test CPU", config={},
                        online={"w": torch.ones(2)}, kind="ema")
    path = policy.save(tmp_path / "ema.pt")
    assert KeptPolicy.load(path).kind == "ema"
    payload = torch.load(path, weights_only=True)
    del payload["kind"]
    torch.save(payload, tmp_path / "old.pt")
    assert KeptPolicy.load(tmp_path / "old.pt").kind == "online"
    payload["kind"] = "best"
    torch.save(payload, tmp_path / "strange.pt")
    with pytest.raises(CheckpointError, match="kind"):
        KeptPolicy.load(tmp_path / "strange.pt")
    with pytest.raises(ValueError, match="policy kind"):
        RunDir(tmp_path).policy(1, "best")
