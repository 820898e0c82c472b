import argparse
import subprocess
import sys

import pytest

from common.config import (
    Config, ConfigError, PRESETS, add_config_arguments, flat_items, load_config,
    parse_config_or_exit, to_toml,
)


def test_paper_preset_holds_the_reference_values():
    config = load_config("paper")
    assert config.learner.lr == 1e-4
    assert config.learner.gamma == 0.99
    assert config.learner.tau == 0.001
    assert (config.learner.batch_size, config.learner.trace_length, config.learner.n_mask) == (10, 10, 7)
    assert config.learner.env_steps_per_update == 4
    assert config.learner.start_episodes == 999
    assert config.learner.total_env_steps == 1_000_000
    assert config.replay.capacity == 1000
    assert config.network.lstm_units == 512 and config.network.n_actions == 5
    assert (config.network.frame_height, config.network.frame_width) == (66, 200)
    assert config.exploration.constant.epsilon == 0.05
    decreasing = config.exploration.decreasing
    assert (decreasing.eps_start, decreasing.eps_last, decreasing.eps_end) == (1.0, 0.1, 0.01)
    assert (decreasing.n_start, decreasing.n_ann, decreasing.n_max) == (50_000, 400_000, 1_000_000)
    assert (config.exploration.vdbe.lam, config.exploration.vdbe.nu) == (0.2, 1.0)
    bmc = config.exploration.bmc
    assert (bmc.alpha0, bmc.a0, bmc.b0, bmc.mu0, bmc.tau0) == (25.0, 250.0, 250.0, 0.0, 1.0)
    assert config.exploration.softmax.kappa == 0.1
    assert (config.exploration.max_boltzmann.epsilon, config.exploration.max_boltzmann.kappa) == (0.05, 0.1)
    assert config.env.reward_beta == 0.8 and config.env.offroad_distance == 3.7 and config.env.max_steps == 2000
    assert config.evaluation.episodes_per_start == 30
    assert config.transport.mode == "peer" and config.transport.multicast_scouting is False


def test_every_preset_is_valid():
    for name in PRESETS:
        load_config(name)


def test_toml_round_trip(tmp_path):
    config = load_config("smoke", overrides={"learner.lr": 3e-4, "transport.connect": ["tcp/127.0.0.1:7447"]})
    path = tmp_path / "config.toml"
    path.write_text(to_toml(config))
    assert load_config("paper", path) == config


def test_overrides_apply_over_file_over_preset(tmp_path):
    path = tmp_path / "config.toml"
    path.write_text("[learner]\nlr = 0.5\nbatch_size = 3\n")
    config = load_config("smoke", path, {"learner.lr": "0.25"})
    assert config.learner.lr == 0.25
    assert config.learner.batch_size == 3
    assert config.replay.capacity == PRESETS["smoke"]["replay.capacity"]


@pytest.mark.parametrize("key, value, message", [
    ("learner.lr", "abc", "learner.lr: expected a number"),
    ("learner.lr", -1, "learner.lr: must be > 0"),
    ("learner.batch_size", "2.5", "learner.batch_size: expected an integer"),
    ("learner.n_mask", 10, "learner.n_mask: must lie in [0, trace_length)"),
    ("exploration.strategy", "greedy", "exploration.strategy: must be one of"),
    ("exploration.bmc.a0", 0, "exploration.bmc.a0: must be > 0"),
    ("exploration.constant.epsilon", 1.5, "exploration.constant.epsilon: must lie in [0, 1]"),
    ("transport.mode", "mesh", "transport.mode: must be"),
    ("transport.multicast_scouting", "maybe", "transport.multicast_scouting: expected true or false"),
    ("run.name", "a/b", "run.name: must be a non-empty key chunk"),
    ("learner.nope", 1, "learner.nope: unknown key"),
    ("nope.lr", 1, "nope.lr: unknown key"),
    ("replay.error_buffer_updates", 0.5, "replay.error_buffer_updates: must be >= 1"),
    ("replay.frame_kb_estimate", 0, "replay.frame_kb_estimate: must be > 0"),
    ("exploration.bmc.observations", "per_batch", "exploration.bmc.observations: must be one of per_step, per_transition"),
    ("learner.start_episodes", 1001, "learner.start_episodes: 1001 exceeds replay.capacity 1000"),
    ("learner.ratio_tolerance", 0.1, "learner.ratio_tolerance: retired key; replaced by replay.error_buffer_updates"),
    ("actor.pace_with_learner", False, "actor.pace_with_learner: retired key; the replay's rate limiter"),
])
def test_bad_values_name_their_key(key, value, message):
    with pytest.raises(ConfigError) as error:
        load_config("paper", overrides={key: value})
    assert str(error.value).startswith(message)
    assert "\n" not in str(error.value)


def test_a_saved_config_with_retired_pacing_keys_still_loads():
    from common.config import from_dict, to_dict
    saved = to_dict(load_config("smoke"))
    saved["learner"]["ratio_tolerance"] = 0.1  # a checkpoint of an earlier version
    saved["actor"]["pace_with_learner"] = True
    assert from_dict(saved) == load_config("smoke")


def test_the_pacing_and_buffer_defaults():
    config = load_config("paper")
    assert config.replay.error_buffer_updates == 50 and config.replay.memory_budget_mb == 16384
    assert config.exploration.bmc.observations == "per_step"
    assert load_config("smoke").replay.error_buffer_updates == 2


def test_bad_toml_file_is_a_config_error(tmp_path):
    path = tmp_path / "bad.toml"
    path.write_text("[learner\nlr = ")
    with pytest.raises(ConfigError, match="invalid TOML"):
        load_config("paper", path)
    with pytest.raises(ConfigError, match="not found"):
        load_config("paper", tmp_path / "missing.toml")


def test_every_field_has_a_command_line_flag():
    parser = argparse.ArgumentParser()
    add_config_arguments(parser)
    args, config = parse_config_or_exit(parser, ["--preset", "smoke", "--learner.lr", "3e-4",
                                                 "--exploration.strategy", "softmax"])
    assert config.learner.lr == 3e-4 and config.exploration.strategy == "softmax"
    flags = {action.option_strings[0] for action in parser._actions if action.option_strings}
    assert {f"--{key}" for key in flat_items(Config())} <= flags


def test_command_line_error_is_one_line_and_exit_2():
    result = subprocess.run([sys.executable, "-m", "learner.main", "--learner.lr", "oops"],
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 2
    assert result.stderr.strip().splitlines() == ["learner: config error: learner.lr: expected a number, got 'oops'"]


def test_each_role_prints_its_resolved_config_at_start():
    # --max-episodes 0: the actor parses, prints its config, and has nothing to run
    result = subprocess.run([sys.executable, "-m", "actor.main", "--preset", "smoke", "--learner.lr", "0.125",
                             "--max-episodes", "0", "--transport.connect", "tcp/127.0.0.1:9"],
                            capture_output=True, text=True, timeout=120)
    assert result.stderr.startswith("actor: resolved config\n")
    assert "  lr = 0.125" in result.stderr and "  [exploration.bmc]" in result.stderr
