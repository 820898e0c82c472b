"""A policy shipped in 16 bits (deploy/tools/ship_policy.py): it reads back as float32 weights within the rounding
of its encoding, acts as the float32 policy does, is half the size, and a damaged one is a clear error."""

import numpy as np
import pytest
import torch

from actor.evaluation.command import build_parser as evaluate_parser, main as evaluate
from actor.evaluation import curve
from actor.evaluation.sources import checkpoint_source
from common.checkpoint import (POLICY_ENCODINGS, Checkpoint, CheckpointError, KeptPolicy,
                               load_checkpoint_or_policy)
from common.config_values import load_config, to_dict
from common.network import D3RQN
from common.run_dir import RunDir
from common.wire.messages import Weights
from deploy.tools import ship_policy
from deploy.bench.weights_encoding import as_sent, drives, q_values
from learner.update import DoubleQLearner
from tests.test_weights_broadcasts import TOLERANCE  # docs/architecture.md's, for compact weights

# the largest change rounding to nearest makes, relative to the value (half a unit in the last place), and the
# absolute one of float16's subnormals (below 6.1e-5), where the relative bound does not hold
ROUNDING = {"float16": (2.0 ** -11, 2.0 ** -25), "bfloat16": (2.0 ** -8, 0.0)}


@pytest.fixture
def config(tmp_path):
    return load_config("smoke", overrides={"run.name": "tiny", "run.runs_dir": str(tmp_path / "runs"),
                                           "network.lstm_units": 16})


def kept(config, path, seed: int = 0) -> KeptPolicy:
    """A float32 kept policy of a freshly initialised network, as the learner writes one."""
    torch.manual_seed(seed)
    policy = KeptPolicy(updates=7, env_steps=280, wall_s=14.0, cpu="Test CPU", config=to_dict(config),
                        online=D3RQN(config.network).state_dict())
    policy.save(path)
    return KeptPolicy.load(path)


def ship(source, out, encoding: str = "float16") -> KeptPolicy:
    ship_policy.main([str(source), "--out", str(out), "--encoding", encoding])
    return KeptPolicy.load(out)


@pytest.mark.parametrize("encoding", ["float16", "bfloat16"])
def test_a_shipped_policy_reads_back_within_its_rounding_at_half_the_size(config, tmp_path, capsys, encoding):
    source = kept(config, RunDir.of(config).policy(7))
    shipped = ship(source.path, tmp_path / "policy.pt", encoding)
    assert "wrote" in capsys.readouterr().out
    assert shipped.encoding == encoding
    assert (shipped.updates, shipped.env_steps, shipped.wall_s, shipped.cpu, shipped.config) == \
        (7, 280, 14.0, "Test CPU", source.config)
    assert all(tensor.dtype == POLICY_ENCODINGS[encoding] for tensor in shipped.online.values())
    relative, absolute = ROUNDING[encoding]
    weights, original = shipped.weights(), source.weights()
    assert sorted(weights) == sorted(original)
    for name, array in weights.items():
        assert array.dtype == np.float32 and array.shape == original[name].shape
        assert np.all(np.abs(array - original[name]) <= relative * np.abs(original[name]) + absolute), name
        # widened exactly: the values torch's rounding to nearest gives
        assert torch.equal(torch.from_numpy(array), source.online[name].to(POLICY_ENCODINGS[encoding]).float())
    ratio = shipped.path.stat().st_size / source.path.stat().st_size
    assert 0.49 < ratio < 0.52  # the config and counts are a few KB of either file


@pytest.fixture(scope="module")
def simulator_frames():
    return drives(load_config("paper").env, frames=120, drive_steps=60)


@pytest.mark.parametrize("encoding", ["float16", "bfloat16"])
def test_the_shipped_policy_acts_as_the_float32_one_within_the_stated_tolerance(tmp_path, simulator_frames, encoding):
    """The paper's network on real frames, each drive from a zeroed state: the weights are those a compact
    broadcast carries, the Q-values move within docs/architecture.md's tolerance, and the greedy action
    changes only where float32's two best Q-values lie within twice the largest move of each other: the
    rounding moves the Q-values a little, so a near-tie may flip, and nothing else does."""
    config = load_config("paper")
    source = kept(config, tmp_path / "float32.pt")
    shipped = ship(source.path, tmp_path / "policy.pt", encoding)
    broadcast = Weights.from_float32(1, source.weights(), encoding).to_float32()
    assert all(np.array_equal(broadcast[name], array) for name, array in shipped.weights().items())
    reference, compact = (q_values(as_sent(config.network, policy.weights(), "float32"), simulator_frames)
                          for policy in (source, shipped))
    moved = np.abs(compact - reference).max()
    share, relative = TOLERANCE[encoding]
    assert 0 < moved <= relative * np.abs(reference).max()
    changed = reference.argmax(axis=1) != compact.argmax(axis=1)
    assert changed.mean() <= share
    best_two = np.sort(reference, axis=1)[:, -2:]
    assert not changed[best_two[:, 1] - best_two[:, 0] > 2 * moved].any()


def test_a_checkpoint_or_its_run_folder_ships_with_its_counts(config, tmp_path):
    learner = DoubleQLearner(config.network, config.learner)
    learner.updates = 12
    run = RunDir.of(config)
    Checkpoint(learner=learner.state_dict(), exploration={}, clock={"env_steps": 3400, "wall_s": 60.5},
               config=to_dict(config)).save(run.checkpoints)
    shipped = ship(run.root, tmp_path / "policy.pt")
    assert (shipped.updates, shipped.env_steps, shipped.wall_s, shipped.cpu) == (12, 3400, 60.5, "unknown")
    online = learner.online.state_dict()
    assert all(torch.equal(shipped.online[name], tensor.half()) for name, tensor in online.items())


def test_evaluate_and_the_curve_read_a_shipped_policy_as_float32_weights(config, tmp_path, monkeypatch):
    source = kept(config, tmp_path / "float32.pt")
    run = RunDir.of(config)
    shipped = ship(source.path, run.policy(7))  # where a run keeps its policies: the curve reads it there
    args = evaluate_parser().parse_args(["--checkpoint", str(shipped.path)])
    found = checkpoint_source(shipped.path, args)
    assert "float16 weights" in found.facts["source"] and found.facts["updates"] == "7"
    assert found.run_dir == run
    for name, array in found.weights.items():
        assert array.dtype == np.float32 and np.array_equal(array, shipped.weights()[name])
    evaluated = []
    monkeypatch.setattr(curve, "evaluate", lambda config, weights, *rest: evaluated.append(weights) or ([], []))
    assert curve.policy_rows(shipped.path, 7, ["test"], lambda saved: curve.curve_config(saved, args), 0,
                             False) == []
    assert len(evaluated) == 1 and all(evaluated[0][name].dtype == np.float32 for name in evaluated[0])


def test_float16_refuses_a_weight_beyond_its_range_and_bfloat16_holds_it(config, tmp_path, capsys):
    source = kept(config, tmp_path / "float32.pt")
    name = next(iter(source.online))
    source.online[name].view(-1)[0] = 1e5
    source.save(tmp_path / "big.pt")
    with pytest.raises(SystemExit) as exit_info:
        ship_policy.main([str(tmp_path / "big.pt"), "--out", str(tmp_path / "policy.pt")])
    assert exit_info.value.code == 1
    error = capsys.readouterr().err
    assert f"ship_policy: error: weights '{name}': a magnitude of 100000 is beyond float16's 65504" in error
    assert not (tmp_path / "policy.pt").exists()
    assert ship(tmp_path / "big.pt", tmp_path / "policy.pt", "bfloat16").weights()  # float32's range
    source.online[name].view(-1)[0] = float("nan")
    with pytest.raises(CheckpointError, match="NaN or infinity"):
        source.compact("float16")
    with pytest.raises(CheckpointError, match="float16 or bfloat16, not 'float32'"):
        source.compact("float32")


def test_a_shipped_policy_is_not_shipped_again(config, tmp_path, capsys):
    shipped = ship(kept(config, tmp_path / "float32.pt").path, tmp_path / "policy.pt")
    with pytest.raises(SystemExit):
        ship_policy.main([str(shipped.path), "--out", str(tmp_path / "again.pt"), "--encoding", "bfloat16"])
    assert "holds float16 weights already" in capsys.readouterr().err


def test_a_damaged_shipped_policy_is_a_clear_error(config, tmp_path, capsys):
    shipped = ship(kept(config, tmp_path / "float32.pt").path, tmp_path / "policy.pt")
    good = shipped.path.read_bytes()
    for damaged in (good[:len(good) // 2], good[:100], b""):
        shipped.path.write_bytes(damaged)
        with pytest.raises(CheckpointError, match="cannot read kept policy .* cut short"):
            KeptPolicy.load(shipped.path)
        with pytest.raises(CheckpointError, match="cannot read checkpoint or policy"):
            load_checkpoint_or_policy(shipped.path)
        with pytest.raises(SystemExit) as exit_info:
            evaluate(["--checkpoint", str(shipped.path)])
        assert exit_info.value.code == 1
        assert "evaluate: error: cannot read checkpoint or policy" in capsys.readouterr().err
    # whole, but with weights of two dtypes, or of integers: not a policy this project wrote
    payload = torch.load(tmp_path / "float32.pt", weights_only=True)
    for online in ({**payload["online"], next(iter(payload["online"])): torch.zeros(2, dtype=torch.float16)},
                   {name: tensor.int() for name, tensor in payload["online"].items()}):
        torch.save({**payload, "online": online}, shipped.path)
        with pytest.raises(CheckpointError, match="online missing or malformed"):
            load_checkpoint_or_policy(shipped.path)
