"""Policy churn (deploy/tools/policy_churn.py): the share of fixed states whose greedy action differs between kept
policies, by hand, and the tool end to end on a tiny run."""

import csv

import numpy as np
import pytest
import torch

from actor.batched_q import BatchedQ
from common.checkpoint import KeptPolicy
from common.config_values import load_config, to_dict
from common.network import D3RQN
from common.run_dir import RunDir
from deploy.tools import policy_churn


def test_pairs_and_churn_by_hand():
    assert policy_churn.pairs([3_000, 1_000, 2_000, 5_000], 1_000) == [(1_000, 2_000), (2_000, 3_000)]
    assert policy_churn.pairs([1_000, 3_000], 1_000) == []
    assert policy_churn.churn(np.array([0, 1, 2, 3]), np.array([0, 1, 0, 0])) == 0.5
    with pytest.raises(ValueError, match="other states"):
        policy_churn.churn(np.array([0, 1]), np.array([0, 1, 2]))


def tiny_config(tmp_path):
    return load_config("smoke", overrides={"run.name": "tiny", "run.runs_dir": str(tmp_path),
                                           "network.lstm_units": 16})


def test_the_greedy_actions_of_a_sequence_are_those_of_stepping_it_from_a_zero_state(tmp_path):
    config = tiny_config(tmp_path)
    torch.manual_seed(3)
    network = D3RQN(config.network)
    rng = np.random.default_rng(0)
    shape = (config.network.frame_height, config.network.frame_width, 3)
    sequences = [rng.integers(0, 256, size=(length, *shape), dtype=np.uint8) for length in (5, 3)]
    stepped = []
    for frames in sequences:
        policy = BatchedQ(network, 1)  # a fresh zero state for each sequence
        stepped.append(torch.stack([policy.q_values([0], [frame])[0] for frame in frames]))
    read = policy_churn.sequence_q_values(network, sequences)
    assert all(torch.allclose(got, want, atol=1e-5) for got, want in zip(read, stepped))
    assert policy_churn.greedy_actions(network, sequences).tolist() == torch.cat(stepped).argmax(dim=-1).tolist()


def keep(config, updates: int, seed: int) -> None:
    torch.manual_seed(seed)
    KeptPolicy(updates=updates, env_steps=4 * updates, wall_s=1.0, cpu="cpu", config=to_dict(config),
               online=D3RQN(config.network).state_dict()).save(RunDir.of(config).policy(updates))


def test_the_tool_reads_each_pair_beside_the_curve(tmp_path, capsys):
    config = tiny_config(tmp_path)
    run = RunDir.of(config)
    keep(config, 100, seed=1)
    keep(config, 200, seed=1)  # the same weights: no churn
    keep(config, 300, seed=2)
    run.curve.mkdir(parents=True)
    with (run.curve / "curve.csv").open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=["updates", "start_set", "cfr", "mean_length", "env_steps",
                                                    "wall_s"])
        writer.writeheader()
        writer.writerows({"updates": u, "start_set": "test", "cfr": cfr, "mean_length": 5, "env_steps": 1, "wall_s": 1}
                         for u, cfr in ((100, 0.5), (200, 0.75)))
    assert policy_churn.main([str(run.root), "--apart", "100", "--steps", "6"]) == 0
    with (run.curve / "churn.csv").open(newline="") as handle:
        rows = list(csv.DictReader(handle))
    assert [(row["updates"], row["next_updates"]) for row in rows] == [("100", "200"), ("200", "300")]
    assert float(rows[0]["churn"]) == 0.0 and float(rows[0]["cfr_change"]) == 0.25
    assert float(rows[1]["churn"]) > 0.0 and rows[1]["cfr_change"] == ""  # 300 is not on the curve
    sequences = policy_churn.probe_frames(config, 6)
    assert int(rows[0]["states"]) == sum(len(frames) for frames in sequences) <= 6 * len(sequences)
    first = policy_churn.greedy_actions(policy_churn.policy_network(run.policy(200)), sequences)
    second = policy_churn.greedy_actions(policy_churn.policy_network(run.policy(300)), sequences)
    assert float(rows[1]["churn"]) == pytest.approx(float(np.mean(first != second)))
    out = capsys.readouterr().out
    assert "online 100 -> 200: churn 0.0%" in out and "online: 2 pairs" in out
    assert policy_churn.main([str(run.root), "--kinds", "ema"]) == 1
    assert "no kept ema policies" in capsys.readouterr().err
