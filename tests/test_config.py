import argparse
import subprocess
import sys
from pathlib import Path

import pytest

from common.config import UPDATE_PATHS, Config
from common.sim_config import CAMERAS
from common.config_cli import add_config_arguments, parse_config_or_exit, parse_flags
from common.config_values import config_fields, flat_items, load_config, to_toml, toml_value
from common.exploration.bmc import BMC_OBSERVATIONS
from common.exploration.names import STRATEGIES
from common.schema.fields import ConfigError
from common.presets import PRESETS


def test_paper_preset_holds_the_reference_values():
    config = load_config("paper")
    assert config.learner.lr == 1e-4
    assert config.learner.gamma == 0.99
    assert config.learner.tau == 0.001
    assert (config.learner.batch_size, config.learner.trace_length, config.learner.n_mask) == (10, 10, 7)
    assert config.pace.env_steps_per_update == 4
    assert config.pace.start_episodes == 999
    assert config.pace.total_env_steps == 1_000_000
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
    ("pace.error_buffer_updates", 0.5, "pace.error_buffer_updates: must be >= 1"),
    ("replay.frame_kb_estimate", 0, "replay.frame_kb_estimate: must be > 0"),
    ("exploration.bmc.observations", "per_batch", "exploration.bmc.observations: must be one of per_step, per_transition"),
    ("pace.start_episodes", 1001, "pace.start_episodes: 1001 exceeds replay.capacity 1000"),
    ("learner.ratio_tolerance", 0.1, "learner.ratio_tolerance: retired key; replaced by pace.error_buffer_updates"),
    ("actor.pace_with_learner", False, "actor.pace_with_learner: retired key; the replay's rate limiter"),
])
def test_bad_values_name_their_key(key, value, message):
    with pytest.raises(ConfigError) as error:
        load_config("paper", overrides={key: value})
    assert str(error.value).startswith(message)
    assert "\n" not in str(error.value)


def test_a_saved_config_with_retired_pacing_keys_still_loads():
    from common.config_values import from_dict, to_dict
    saved = to_dict(load_config("smoke"))
    saved["learner"]["ratio_tolerance"] = 0.1  # a checkpoint of an earlier version
    saved["actor"]["pace_with_learner"] = True
    assert from_dict(saved) == load_config("smoke")


def test_a_config_with_the_pace_in_its_earlier_sections_loads_into_pace(tmp_path):
    """Run folders, checkpoints and users' files written before the pace had its own section."""
    from common.config_values import from_dict, to_dict
    saved = to_dict(load_config("smoke"))
    pace = saved.pop("pace")
    saved["learner"].update(total_env_steps=12_345, start_by="steps", start_steps=pace["start_steps"],
                            env_steps_per_update=pace["env_steps_per_update"], start_episodes=pace["start_episodes"])
    saved["replay"].update(error_buffer_updates=7.0, hold_updates=pace["hold_updates"])
    loaded = from_dict(saved)
    assert (loaded.pace.total_env_steps, loaded.pace.start_by, loaded.pace.error_buffer_updates) == (12_345, "steps", 7.0)
    old_file = tmp_path / "old.toml"
    old_file.write_text("[learner]\ntotal_env_steps = 777\n[replay]\nhold_updates = 3.0\n")
    assert (load_config("smoke", old_file).pace.total_env_steps, load_config("smoke", old_file).pace.hold_updates) \
        == (777, 3.0)
    parser = argparse.ArgumentParser()
    add_config_arguments(parser)
    _, config = parse_config_or_exit(parser, ["--preset", "smoke", "--learner.total_env_steps", "999"])
    assert config.pace.total_env_steps == 999


def test_the_pacing_and_buffer_defaults():
    config = load_config("paper")
    assert config.pace.error_buffer_updates == 50 and config.replay.memory_budget_mb == 16384
    assert config.exploration.bmc.observations == "per_step"
    assert load_config("smoke").pace.error_buffer_updates == 2


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


# --- the help text, taken from each field's option() documentation ---------------------------------

# A name part that spells a unit; the field must declare that unit.
UNIT_OF_NAME_PART = {"s": "s", "m": "m", "mb": "MB", "kb": "KB", "deg": "degrees", "frequency": "Hz", "speed": "m/s"}

ENUMERATED = {
    "exploration.strategy": STRATEGIES,
    "env.camera": CAMERAS,
    "network.device": ("auto", "cpu", "cuda[:N]"),
    "learner.update_path": UPDATE_PATHS,
    "exploration.bmc.observations": BMC_OBSERVATIONS,
    "transport.mode": ("peer", "client", "router"),
    "recorder.image_format": ("png", "jpeg"),
    "learner.weights_encoding": ("float32", "float16", "bfloat16"),
    "learner.keep_encoding": ("float32", "float16", "bfloat16"),
    "actor.inference": ("float32", "bfloat16", "auto"),
    "learner.precision": ("float32", "bfloat16", "auto"),
    "pace.start_by": ("strategy", "episodes", "steps"),
}


def help_entries(text: str) -> dict[str, str]:
    """--help output as {flag: its whole entry, whitespace collapsed}."""
    entries: dict[str, list[str]] = {}
    current = None
    for line in text.splitlines():
        if line.startswith("  --"):
            current = line.split()[0]
            entries[current] = [line]
        elif current is not None and line.startswith("    "):
            entries[current].append(line)
        else:
            current = None
    return {flag: " ".join(" ".join(lines).split()) for flag, lines in entries.items()}


def config_help(capsys, *argv: str) -> str:
    parser = argparse.ArgumentParser(prog="prog")
    add_config_arguments(parser)
    with pytest.raises(SystemExit) as stop:
        parser.parse_args([*argv, "--help"])
    assert stop.value.code == 0
    return capsys.readouterr().out


def test_every_field_has_a_doc_and_the_unit_its_name_spells():
    fields = config_fields()
    assert set(fields) == set(flat_items(Config()))
    for key, f in fields.items():
        assert f.metadata["doc"].strip(), f"{key} has no documentation"
        implied = {UNIT_OF_NAME_PART[part] for part in f.name.split("_") if part in UNIT_OF_NAME_PART}
        assert implied <= {f.metadata["unit"]}, f"{key}: unit {f.metadata['unit']!r}, its name says {implied}"


def test_enumerated_fields_list_exactly_the_values_validation_accepts():
    fields = config_fields()
    assert {key for key, f in fields.items() if f.metadata["choices"]} == set(ENUMERATED)
    for key, choices in ENUMERATED.items():
        assert fields[key].metadata["choices"] == choices
        for choice in choices:
            load_config("paper", overrides={key: choice.replace("[:N]", ":1")})
        with pytest.raises(ConfigError, match=key):
            load_config("paper", overrides={key: "none-of-these"})


def test_help_shows_each_options_doc_unit_choices_and_default(capsys):
    entries = help_entries(config_help(capsys))
    defaults = flat_items(Config())
    for key, f in config_fields().items():
        entry = entries[f"--{key}"]
        first_words = " ".join(f.metadata["doc"].split()[:3])
        assert first_words in entry, (key, entry)
        assert entry.endswith(f"(default: {toml_value(defaults[key])})"), (key, entry)
        if f.metadata["unit"]:
            assert f"[{f.metadata['unit']}]" in entry, (key, entry)
    assert entries["--exploration.strategy"].startswith("--exploration.strategy {" + ",".join(STRATEGIES) + "}")
    assert entries["--env.camera"].startswith("--env.camera {front,topdown}")


def test_help_shows_the_defaults_of_the_chosen_preset(capsys):
    paper = help_entries(config_help(capsys))
    local = help_entries(config_help(capsys, "--preset", "local"))
    assert paper["--pace.total_env_steps"].endswith("(default: 1000000)")
    assert local["--pace.total_env_steps"].endswith("(default of preset local: 60000)")
    assert local["--learner.lr"].endswith("(default: 0.0001)")  # local keeps the paper's


def test_the_fast_preset_is_local_but_for_the_deviations_its_help_names(capsys):
    local, fast = flat_items(load_config("local")), flat_items(load_config("fast"))
    changed = sorted(key for key in fast if fast[key] != local[key])
    assert changed == ["learner.precision", "pace.total_env_steps"]
    assert all(key in PRESETS["fast"].doc for key in ("learner.precision auto", "112,000 env steps"))
    entries = help_entries(config_help(capsys, "--preset", "fast"))
    assert entries["--learner.precision"].endswith(f"(default of preset fast: {toml_value('auto')})")


def test_help_lists_the_presets_and_what_each_changes(capsys):
    text = " ".join(config_help(capsys).split())
    for name, preset in PRESETS.items():
        assert f"preset {name}: {preset.doc}" in text
        for key, value in preset.items():
            assert f"{key} = {toml_value(value)}" in text


def test_the_stack_help_follows_its_preset():
    stack = Path(__file__).resolve().parents[1] / "deploy" / "launcher" / "stack.py"
    result = subprocess.run([sys.executable, str(stack), "--preset", "local", "--help"],
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 0
    assert help_entries(result.stdout)["--pace.total_env_steps"].endswith("(default of preset local: 60000)")


@pytest.mark.parametrize("argv, typed, suggestion", [
    (["--run.nam", "x"], "--run.nam x", "--run.name"),  # an abbreviation argparse would have taken
    (["--learner.lrr=3e-4"], "--learner.lrr=3e-4", "--learner.lr"),
    (["--exploraton.strategy", "vdbe"], "--exploraton.strategy vdbe", "--exploration.strategy"),
    (["--dump-conf"], "--dump-conf", "--dump-config"),
])
def test_an_unknown_or_abbreviated_flag_is_refused_with_a_suggestion(capsys, argv, typed, suggestion):
    parser = argparse.ArgumentParser(prog="prog")
    add_config_arguments(parser)
    with pytest.raises(SystemExit) as stop:
        parse_config_or_exit(parser, argv)
    assert stop.value.code == 2
    last = capsys.readouterr().err.strip().splitlines()[-1]
    flag = typed.split()[0].split("=")[0]
    assert last == f"prog: error: unrecognized arguments: {typed}; {flag}: did you mean {suggestion}?"


def test_a_subcommands_unknown_flag_gets_the_suggestion_too(capsys):
    from replay.recorder.cli import build_parser
    with pytest.raises(SystemExit):
        parse_flags(build_parser(), ["record", "--run.nam", "x"])
    assert capsys.readouterr().err.strip().endswith("--run.nam: did you mean --run.name?")


def test_full_flag_names_still_set_their_keys():
    parser = argparse.ArgumentParser()
    add_config_arguments(parser)
    _, config = parse_config_or_exit(parser, ["--run.name=x", "--preset", "local", "--env.camera", "topdown"])
    assert (config.run.name, config.env.camera, config.pace.total_env_steps) == ("x", "topdown", 60_000)


def test_a_config_with_the_recorders_earlier_section_name_loads():
    from common.config_values import from_dict, to_dict
    saved = to_dict(load_config("smoke"))
    saved["record"] = {**saved.pop("recorder"), "enabled": False, "chunk_mb": 3.0}
    loaded = from_dict(saved)
    assert (loaded.recorder.enabled, loaded.recorder.chunk_mb) == (False, 3.0)
