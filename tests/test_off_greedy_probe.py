"""deploy/tools/off_greedy_probe.py: each rule's chance of leaving argmax Q, by hand, and the probe on a policy."""

import math

import pytest
import torch

from common.checkpoint import KeptPolicy
from common.config_values import load_config, to_dict
from common.network import D3RQN
from deploy.tools import off_greedy_probe


def test_each_rules_chance_of_another_action_by_hand():
    rows = [[1.0, 0.9, 0.0], [5.0, 5.0 - 10.0, 5.0 - 20.0]]  # gaps 0.1 and 10: near a tie, and far apart
    near = 1 - 1 / (1 + math.exp(-1) + math.exp(-10))  # softmax(Q / 0.1): 0.26896
    assert off_greedy_probe.rule_off_greedy(rows, 1.0, 0.1) == pytest.approx((near + 0.0) / 2, abs=1e-12)
    assert off_greedy_probe.rule_off_greedy(rows, 0.05, 0.1) == pytest.approx(0.05 * near / 2, abs=1e-12)
    assert off_greedy_probe.rule_off_greedy(rows, 0.05, 0.0) == pytest.approx(0.05 * 2 / 3)  # uniform: 2 of 3


def test_the_probe_drives_a_policy_and_reads_the_runs_rules(tmp_path, capsys):
    config = load_config("smoke", overrides={"network.lstm_units": 16, "exploration.max_boltzmann.epsilon": 0.2})
    torch.manual_seed(0)
    path = KeptPolicy(updates=5, env_steps=200, wall_s=1.0, cpu="Test CPU", config=to_dict(config),
                      online=D3RQN(config.network).state_dict()).save(tmp_path / "policy.pt")
    assert off_greedy_probe.main([str(path), "--starts", "2", "--steps", "4"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith("8 greedy steps")  # 4 from each start: none ended sooner
    assert [line.split()[0] for line in lines[1:]] == ["softmax", "max_boltzmann", "constant"]
    softmax, boltzmann = (float(line.split()[-3].rstrip("%")) for line in lines[1:3])
    assert "epsilon 0.2, kappa 0.1" in lines[2] and boltzmann == pytest.approx(0.2 * softmax, abs=0.01)
    assert lines[3].endswith("4.00% of steps")  # 0.05 * 4 / 5


@pytest.mark.parametrize("flags, said", [(["--starts", "0"], "--starts must lie in 1..10"),
                                         ([], "no checkpoint at")])
def test_a_bad_flag_or_file_is_one_line(tmp_path, capsys, flags, said):
    assert off_greedy_probe.main([str(tmp_path / "nothing.pt"), *flags]) == 1
    assert said in capsys.readouterr().err
