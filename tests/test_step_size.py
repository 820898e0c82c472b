"""The late decay of the learning rate and the gradient-norm clip (learner/step_size.py), beyond the paper: values
computed by hand, and the learner applying them."""

import dataclasses

import pytest
import torch

from common.config import LearnerConfig
from common.schema.fields import ConfigError
from learner.step_size import clip_gradient, learning_rate, set_learning_rate
from tests.test_learner_resume import batches, config, train  # noqa: F401 (config: a fixture)
from learner.service import LearnerService

DECAY = LearnerConfig(lr=1e-4, lr_decay_from=100, lr_decay_to=200, lr_final_scale=0.1)


@pytest.mark.parametrize("updates, rate", [
    (0, 1e-4), (100, 1e-4),  # before and at the decay's start: the paper's rate
    (150, 5.5e-5),  # halfway: 1e-4 x (1 - 0.5 x 0.9)
    (190, 1.9e-5),  # 1e-4 x (1 - 0.9 x 0.9)
    (200, 1e-5), (10_000, 1e-5),  # the end and after: lr x lr_final_scale
])
def test_the_rate_falls_linearly_from_decay_from_to_decay_to_by_hand(updates, rate):
    assert learning_rate(DECAY, updates) == pytest.approx(rate, rel=1e-12)


def test_without_the_decay_the_optimiser_is_left_as_built():
    network = torch.nn.Linear(2, 1)
    optimizer = torch.optim.Adam(network.parameters(), lr=3e-4)
    set_learning_rate(optimizer, LearnerConfig(lr=1e-4), 10_000)
    assert optimizer.param_groups[0]["lr"] == 3e-4
    set_learning_rate(optimizer, DECAY, 150)
    assert optimizer.param_groups[0]["lr"] == pytest.approx(5.5e-5)


def test_the_clip_scales_the_gradient_to_its_norm_by_hand():
    weight = torch.nn.Parameter(torch.zeros(2))
    weight.grad = torch.tensor([3.0, 4.0])  # norm 5
    clip_gradient([weight], LearnerConfig(grad_clip_norm=0.0))
    assert weight.grad.tolist() == [3.0, 4.0]  # off
    clip_gradient([weight], LearnerConfig(grad_clip_norm=10.0))
    assert weight.grad.tolist() == [3.0, 4.0]  # within the bound
    clip_gradient([weight], LearnerConfig(grad_clip_norm=1.0))
    assert weight.grad.tolist() == pytest.approx([0.6, 0.8], rel=1e-5)


@pytest.mark.parametrize("overrides, message", [
    ({"lr_decay_from": 100, "lr_decay_to": 100}, "lr_decay_to"),
    ({"lr_final_scale": 0.0}, "lr_final_scale"),
    ({"grad_clip_norm": -1.0}, "grad_clip_norm"),
    ({"lr_decay_from": -5}, "lr_decay_from"),
])
def test_wrong_values_are_refused(overrides, message):
    with pytest.raises(ConfigError, match=message):
        dataclasses.replace(LearnerConfig(), **overrides).validate()


def gradient_norm(service: LearnerService) -> float:
    grads = [parameter.grad for parameter in service.learner.online.parameters() if parameter.grad is not None]
    return float(torch.linalg.vector_norm(torch.stack([torch.linalg.vector_norm(grad) for grad in grads])))


def test_the_learner_clips_and_decays_its_steps(config):
    plain = LearnerService(config)
    plain.start_updates()
    train(plain, batches(1)[0])
    assert gradient_norm(plain) > 1e-3
    config.learner.grad_clip_norm = 1e-3
    config.learner.lr_decay_from, config.learner.lr_decay_to, config.learner.lr_final_scale = 1, 3, 0.5
    service = LearnerService(config)
    service.start_updates()
    for batch in batches(3):
        train(service, batch)
    assert gradient_norm(service) == pytest.approx(1e-3, rel=1e-4)  # the last update's gradient, clipped
    # the third update followed 2 updates: halfway from 1 to 3, lr x (1 - 0.5 x 0.5)
    assert service.learner.optimizer.param_groups[0]["lr"] == pytest.approx(config.learner.lr * 0.75)


def test_the_norm_is_measured_before_the_clip_and_measuring_only_reads():
    weight = torch.nn.Parameter(torch.zeros(2))
    weight.grad = torch.tensor([3.0, 4.0])  # norm 5
    assert clip_gradient([weight], LearnerConfig()) is None  # neither clipped nor asked
    assert clip_gradient([weight], LearnerConfig(), measure=True) == pytest.approx(5.0)
    assert weight.grad.tolist() == [3.0, 4.0]
    assert clip_gradient([weight], LearnerConfig(grad_clip_norm=1.0)) == pytest.approx(5.0)  # the norm it clipped


def test_the_learner_reports_the_norm_every_few_updates_and_trains_as_without(config, monkeypatch):
    import learner.update as update

    def run(every: int):
        monkeypatch.setattr(update, "GRAD_NORM_EVERY", every)
        service = LearnerService(config)
        service.start_updates()
        norms = [service.train_on(batch).grad_norm for batch in batches(3)]
        return norms, service, gradient_norm(service)

    norms, measured, last = run(1)
    assert all(norm is not None for norm in norms) and norms[-1] == pytest.approx(last, rel=1e-5)
    norms, unmeasured, _ = run(2)
    assert norms[0] is not None and norms[1] is None and norms[2] is not None  # updates 0 and 2 of 0, 1, 2
    for one, other in zip(measured.learner.online.parameters(), unmeasured.learner.online.parameters()):
        assert torch.equal(one, other)
