"""The mean of kept policies' weights (deploy/tools/average_policies.py): hand-computed means, the file names what it
averages, and what cannot be averaged is refused with the reason."""

from pathlib import Path

import pytest
import torch

from actor.evaluation.command import build_parser as evaluate_parser
from actor.evaluation.sources import checkpoint_source
from common.checkpoint import CheckpointError, KeptPolicy, write_atomically
from common.config_values import load_config, to_dict
from common.network import D3RQN
from common.run_dir import RunDir
from deploy.tools import average_policies


@pytest.fixture
def config(tmp_path):
    return load_config("smoke", overrides={"run.name": "tiny", "run.runs_dir": str(tmp_path / "runs"),
                                           "network.lstm_units": 16})


def filled(config, updates: int, value: float, path) -> KeptPolicy:
    """A kept policy whose every weight is `value`, kept at `updates`."""
    online = {name: torch.full_like(tensor, value) for name, tensor in D3RQN(config.network).state_dict().items()}
    return KeptPolicy(updates=updates, env_steps=4 * updates, wall_s=updates / 8, cpu="Test CPU",
                      config=to_dict(config), online=online).save(path)


def test_the_mean_is_taken_weight_by_weight_and_dated_as_the_latest(config, tmp_path, capsys):
    run = RunDir.of(config)
    run.policies.mkdir(parents=True)
    for updates, value in [(1000, 9.0), (2000, 1.0), (3000, -2.0), (4000, 0.5)]:
        filled(config, updates, value, run.policy(updates))
    out = tmp_path / "averaged" / "last3.pt"
    average_policies.main([str(run.root), "--last", "3", "--out", str(out)])
    assert "the mean of 3 kept policies' weights" in capsys.readouterr().out
    mean = KeptPolicy.load(out)
    assert mean.averaged == (2000, 3000, 4000)
    assert (mean.updates, mean.env_steps, mean.wall_s, mean.encoding) == (4000, 16000, 500.0, "float32")
    for tensor in mean.online.values():  # (1 - 2 + 0.5) / 3
        assert torch.allclose(tensor, torch.full_like(tensor, -0.5 / 3))


def test_files_of_mixed_encodings_are_widened_before_the_mean(config, tmp_path):
    first = KeptPolicy.load(filled(config, 10, 0.25, tmp_path / "a.pt"))
    first.compact("float16").save(tmp_path / "a16.pt")  # 0.25 is exact in float16
    filled(config, 20, 0.75, tmp_path / "b.pt")
    out = tmp_path / "mean.pt"
    average_policies.main([str(tmp_path / "a16.pt"), str(tmp_path / "b.pt"), "--out", str(out)])
    mean = KeptPolicy.load(out)
    assert mean.averaged == (10, 20) and mean.updates == 20
    assert all(torch.equal(tensor, torch.full_like(tensor, 0.5)) for tensor in mean.online.values())


def test_evaluate_names_the_policies_a_mean_was_made_of(config, tmp_path):
    filled(config, 10, 0.0, tmp_path / "a.pt")
    filled(config, 20, 0.0, tmp_path / "b.pt")
    average_policies.main([str(tmp_path / "a.pt"), str(tmp_path / "b.pt"), "--out", str(tmp_path / "mean.pt")])
    args = evaluate_parser().parse_args(["--checkpoint", str(tmp_path / "mean.pt")])
    facts = checkpoint_source(tmp_path / "mean.pt", args).facts
    assert facts["averaged"] == "the mean of 2 kept policies' weights, updates 10, 20"
    single = checkpoint_source(tmp_path / "a.pt", args).facts
    assert "averaged" not in single  # a learner's kept policy says nothing of means


def refused(argv, capsys) -> str:
    with pytest.raises(SystemExit) as stop:
        average_policies.main(argv)
    assert stop.value.code == 1
    return capsys.readouterr().err


def test_what_cannot_be_averaged_is_refused_with_the_reason(config, tmp_path, capsys):
    filled(config, 10, 0.0, tmp_path / "a.pt")
    other = load_config("smoke", overrides={"network.lstm_units": 8})
    filled(other, 20, 0.0, tmp_path / "small.pt")
    out = str(tmp_path / "mean.pt")
    assert "another network" in refused([str(tmp_path / "a.pt"), str(tmp_path / "small.pt"), "--out", out], capsys)
    assert "at least two" in refused([str(tmp_path / "a.pt"), "--out", out], capsys)
    assert "no kept policies" in refused([str(tmp_path), "--out", out], capsys)
    assert "--last must be at least 1" in refused([str(tmp_path / "a.pt"), "--last", "0", "--out", out], capsys)
    (tmp_path / "runs" / "policies").mkdir(parents=True)
    assert "policies/ folder" in refused([str(tmp_path / "a.pt"), str(tmp_path / "a.pt"), "--out",
                                          str(tmp_path / "runs" / "policies" / "mean.pt")], capsys)
    average_policies.main([str(tmp_path / "a.pt"), str(tmp_path / "a.pt"), "--out", out])
    assert "a mean policy: the mean is of kept online policies" in refused(
        [out, str(tmp_path / "a.pt"), "--out", str(tmp_path / "x.pt")], capsys)
    assert KeptPolicy.load(Path(out)).kind == "mean"
    assert not (tmp_path / "x.pt").exists()


def test_a_kept_policy_with_a_malformed_list_of_averaged_updates_is_a_clear_error(config, tmp_path):
    path = filled(config, 10, 0.0, tmp_path / "a.pt")
    payload = torch.load(path, weights_only=False)
    assert "averaged" not in payload  # the learner's files are as before
    write_atomically(path, {**payload, "averaged": [10, -1]})
    with pytest.raises(CheckpointError, match="averaged missing or malformed"):
        KeptPolicy.load(path)
