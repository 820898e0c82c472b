"""Writes an evaluation to disk: per-episode CSV, summary CSV, a Markdown table and the config."""

from __future__ import annotations

import csv
import dataclasses
from pathlib import Path
from typing import Sequence

from actor.evaluation_stats import EvaluationEpisode, SetSummary

EPISODES_CSV = "episodes.csv"
SUMMARY_CSV = "summary.csv"
SUMMARY_MD = "summary.md"
CONFIG_TOML = "config.toml"

COLUMN_LEGEND = (
    ("Episodes", "episodes run: episodes_per_start trials from each start of the set"),
    ("Mean / Std / Min length", "episode length in steps (population std); the cap is an episode's maximum"),
    ("CFR", "collision-free rate: share of episodes that reach the step cap without a collision"),
    ("Collision / Off-road", "share of episodes ended by hitting an obstacle / by leaving the road "
                             "(more than offroad_distance from the centre-line)"),
    ("Reward/step", "mean step reward exp(-beta d), pooled over all steps of the set"),
    ("r in [a, b)", "share of all steps whose reward fell in the bin; the last bin holds the near-optimal steps"),
    ("Distinct/start", "different trajectories among the trials of one start, averaged over starts"),
)


def bin_labels(edges: Sequence[float]) -> list[str]:
    """'[0, 0.25)', ..., '[0.75, 1]': half-open bins except the last."""
    pairs = list(zip(edges, edges[1:]))
    return [f"[{low:g}, {high:g}{']' if number == len(pairs) - 1 else ')'}" for number, (low, high) in enumerate(pairs)]


def _bin_keys(prefix: str, edges: Sequence[float]) -> list[str]:
    return [f"{prefix}_{low:g}_{high:g}" for low, high in zip(edges, edges[1:])]


def write_episodes_csv(path: Path, episodes: Sequence[EvaluationEpisode], edges: Sequence[float]) -> None:
    plain = [field.name for field in dataclasses.fields(EvaluationEpisode) if field.name != "reward_bin_counts"]
    with path.open("w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow([*plain, "collision_free", *_bin_keys("steps", edges)])
        for episode in episodes:
            writer.writerow([*(getattr(episode, name) for name in plain), episode.collision_free,
                             *episode.reward_bin_counts])


def write_summary_csv(path: Path, summaries: Sequence[SetSummary], edges: Sequence[float]) -> None:
    plain = [field.name for field in dataclasses.fields(SetSummary) if field.name != "reward_shares"]
    with path.open("w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow([*plain, *_bin_keys("share", edges)])
        for summary in summaries:
            writer.writerow([*(getattr(summary, name) for name in plain), *summary.reward_shares])


def markdown_table(summaries: Sequence[SetSummary], edges: Sequence[float]) -> str:
    header = ["Policy", "Set", "Episodes", "Mean length", "Std", "Min", "CFR", "Collision", "Off-road",
              "Reward/step", *(f"r in {label}" for label in bin_labels(edges)), "Distinct/start"]
    rows = [[s.policy, s.start_set, str(s.episodes), f"{s.mean_length:.2f}", f"{s.std_length:.2f}",
             str(s.min_length), _percent(s.cfr), _percent(s.collision_share), _percent(s.offroad_share),
             f"{s.mean_reward_per_step:.3f}", *(_percent(share) for share in s.reward_shares),
             f"{s.distinct_per_start:.2f}"] for s in summaries]
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(row) + " |" for row in rows]
    return "\n".join(lines)


def greedy_variety_note(summaries: Sequence[SetSummary], trials: int) -> str:
    """What the measured trajectories say about the greedy trials' variety."""
    greedy = [summary for summary in summaries if summary.policy == "greedy"]
    if not greedy:
        return ""
    if trials == 1:
        return "One trial per start: nothing to say about the variety of repeated trials."
    if all(summary.distinct_per_start == 1.0 for summary in greedy):
        return (f"The {trials} greedy trials from each start were all identical. The simulator has no "
                "randomness (a start pose and the actions fix the episode) and the greedy policy none "
                "either, so the trials repeat one episode despite their different seeds; the spread of "
                "the greedy rows comes from the different starts only.")
    found = ", ".join(f"{s.start_set} {s.distinct_per_start:.2f}" for s in greedy)
    return f"Greedy trials from one start differed: distinct trajectories per start (of {trials}): {found}."


def markdown_report(summaries: Sequence[SetSummary], edges: Sequence[float], facts: dict[str, str],
                    trials: int) -> str:
    lines = ["# Evaluation", ""]
    lines += [f"- {name}: {value}" for name, value in facts.items()]
    lines += ["", markdown_table(summaries, edges), ""]
    note = greedy_variety_note(summaries, trials)
    if note:
        lines += [note, ""]
    lines += ["Columns:", ""]
    lines += [f"- **{name}**: {meaning}" for name, meaning in COLUMN_LEGEND]
    return "\n".join(lines) + "\n"


def write_report(out_dir: Path, episodes: Sequence[EvaluationEpisode], summaries: Sequence[SetSummary],
                 edges: Sequence[float], facts: dict[str, str], trials: int, config_toml: str) -> list[Path]:
    """Writes the four files (the config the evaluation ran with last); returns their paths."""
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = [out_dir / EPISODES_CSV, out_dir / SUMMARY_CSV, out_dir / SUMMARY_MD, out_dir / CONFIG_TOML]
    write_episodes_csv(paths[0], episodes, edges)
    write_summary_csv(paths[1], summaries, edges)
    paths[2].write_text(markdown_report(summaries, edges, facts, trials))
    paths[3].write_text(config_toml)
    return paths


def _percent(share: float) -> str:
    return f"{100 * share:.2f}%"
