"""Study run folders for the report tests: a config and a greedy test curve of given mean lengths."""

import csv

from common.config_values import load_config, to_toml


def write_run(top, name, seed, overrides, lengths, seconds_per_policy=100.0, cpu="cpu"):
    """A run folder with a config and a greedy test curve of the given mean lengths at 1,000, 2,000, ... updates,
    a policy kept every `seconds_per_policy` on `cpu`."""
    folder = top / f"{name}-s{seed}"
    folder.mkdir(parents=True)
    folder.joinpath("config.toml").write_text(to_toml(load_config("local", overrides={"run.seed": seed, **overrides})))
    columns = ["updates", "env_steps", "wall_s", "kept_file", "trained_on", "start_set", "mean_length",
               "mean_length_low", "mean_length_high", "cfr"]
    with folder.joinpath("curve.csv").open("w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(columns)
        for k, length in enumerate(lengths, start=1):
            writer.writerow([1000 * k, 4000 * k, seconds_per_policy * k, f"policy-u{1000 * k:07d}.pt", cpu, "test",
                             length, length - 10, length + 10, min(length / 2000, 1.0)])
    return folder
