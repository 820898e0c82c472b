"""Writes an evaluation to disk: per-episode CSV, summary CSV, a Markdown table and the config."""

from __future__ import annotations

import csv
import dataclasses
import json
import math
import statistics
from pathlib import Path
from typing import Sequence

from common.analysis.stats import TERMINAL_REASONS, EvaluationEpisode, SetSummary

EPISODES_CSV = "episodes.csv"
SUMMARY_CSV = "summary.csv"
SUMMARY_MD = "summary.md"
CONFIG_TOML = "config.toml"
FACTS_JSON = "facts.json"  # where the weights came from (updates, env steps, strategy, ...), read by the comparison

# The SetSummary field of each statistic that has an interval (intervals.STATISTICS).
INTERVAL_FIELDS = {"mean_length": "mean_length", "iqm_length": "iqm_length", "cfr": "cfr",
                   "progress_m": "mean_progress_m", "streets": "mean_streets", "junctions": "mean_junctions",
                   "reward_per_step": "mean_reward_per_step"}
# The statistics of an episode's coverage, which evaluations gained after the others (files written before
# have none), and their summary columns.
COVERAGE = ("streets", "junctions")
COVERAGE_COLUMNS = tuple(column for statistic in COVERAGE
                         for column in (INTERVAL_FIELDS[statistic], f"{statistic}_low", f"{statistic}_high"))

COLUMN_LEGEND = (
    ("Episodes", "episodes run: episodes_per_start trials from each start of the set"),
    ("Mean / Std / Min length", "episode length in steps (population std); the cap is an episode's maximum"),
    ("IQM", "interquartile mean of the episode lengths: the mean of the middle half"),
    ("CFR", "collision-free rate: share of episodes that reach the step cap (every other end is a failure)"),
    ("Collision / Off-road / Stalled", "share of episodes ended by hitting an obstacle / by leaving the road "
                                       "(more than offroad_distance from the centre-line) / by making no "
                                       "progress along the road over the simulator's window"),
    ("Progress", "metres driven along the road network per episode, in the direction of travel "
                 "(– where the simulator does not report it)"),
    ("Streets / Junctions", "distinct streets driven along / junctions turned at or crossed per episode, "
                            "the mean: a driver looping one block reaches the cap over 4 of each"),
    ("Reward/step", "mean step reward exp(-beta d), pooled over all steps of the set"),
    ("[low, high]", "confidence interval by stratified bootstrap: training runs resampled whole, then each "
                    "run's trials within each start (common/analysis/intervals.py); with one run it shows "
                    "only the spread of the trials"),
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


def summary_columns(summary: SetSummary, edges: Sequence[float]) -> dict[str, object]:
    """A summary row as flat CSV columns: each interval as <statistic>_low and <statistic>_high."""
    statistic_of = {name: statistic for statistic, name in INTERVAL_FIELDS.items()}
    columns: dict[str, object] = {}
    for field in dataclasses.fields(SetSummary):
        if field.name in ("reward_shares", "intervals"):
            continue
        columns[field.name] = getattr(summary, field.name)
        if field.name in statistic_of:
            interval = summary.intervals[statistic_of[field.name]]
            columns[f"{statistic_of[field.name]}_low"] = interval.low
            columns[f"{statistic_of[field.name]}_high"] = interval.high
    columns.update(zip(_bin_keys("share", edges), summary.reward_shares))
    return columns


def write_summary_csv(path: Path, summaries: Sequence[SetSummary], edges: Sequence[float]) -> None:
    rows = [summary_columns(summary, edges) for summary in summaries]
    with path.open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(rows[0]) if rows else [])
        writer.writeheader()
        writer.writerows(rows)


def with_interval(summary: SetSummary, statistic: str, percent: bool = False, digits: int = 2) -> str:
    """'812.40 [701.20, 905.00]' or '12.00% [8.33, 15.67]'; '–' for a value the evaluation has not got."""
    value = getattr(summary, INTERVAL_FIELDS[statistic])
    interval = summary.intervals[statistic]
    if not math.isfinite(value):
        return "–"
    scale, unit = (100.0, "%") if percent else (1.0, "")
    text = f"{scale * value:,.{digits}f}{unit}"
    if math.isfinite(interval.low):
        text += f" [{scale * interval.low:,.{digits}f}, {scale * interval.high:,.{digits}f}]"
    return text


def markdown_table(summaries: Sequence[SetSummary], edges: Sequence[float], confidence: float = 0.95) -> str:
    level = f"{100 * confidence:g}% CI"
    header = ["Policy", "Set", "Episodes", f"Mean length [{level}]", f"IQM [{level}]", "Std", "Min",
              f"CFR [{level}]", "Collision", "Off-road", "Stalled", f"Progress m [{level}]",
              f"Streets [{level}]", f"Junctions [{level}]",
              f"Reward/step [{level}]", *(f"r in {label}" for label in bin_labels(edges)), "Distinct/start"]
    rows = [[s.policy, s.start_set, str(s.episodes), with_interval(s, "mean_length"), with_interval(s, "iqm_length"),
             f"{s.std_length:.2f}", str(s.min_length), with_interval(s, "cfr", percent=True),
             _percent(s.collision_share), _percent(s.offroad_share), _percent(s.stalled_share),
             with_interval(s, "progress_m", digits=1), with_interval(s, "streets"),
             with_interval(s, "junctions"), with_interval(s, "reward_per_step", digits=3),
             *(_percent(share) for share in s.reward_shares), f"{s.distinct_per_start:.2f}"] for s in summaries]
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


def failures_by_start(episodes: Sequence[EvaluationEpisode], policy: str = "greedy") -> list[str]:
    """Where a policy's episodes failed, start by start: a set's CFR can hide a few starts that fail most
    trials at one spot (the long run: test start 3 failed 8 of 30 trials, all at steps 49-50)."""
    by_start: dict[tuple[str, int], list[EvaluationEpisode]] = {}
    for episode in episodes:
        if episode.policy == policy:
            by_start.setdefault((episode.start_set, episode.start_index), []).append(episode)
    failed = {key: [episode for episode in trials if not episode.collision_free] for key, trials in by_start.items()}
    if not by_start:
        return []
    if not any(failed.values()):
        return [f"Every {policy} episode reached the cap."]
    lines = [f"Where the {policy} policy failed (starts with a failure only):", "",
             "| Set | Start | Collision-free | Collision / off-road / stalled | Failed at step: median (range) |",
             "|---|---:|---:|---:|---:|"]
    for (start_set, start), ended in sorted(failed.items()):
        if not ended:
            continue
        ends = " / ".join(str(sum(episode.end == reason for episode in ended)) for reason in TERMINAL_REASONS)
        steps = [episode.length for episode in ended]
        total = len(by_start[(start_set, start)])
        lines.append(f"| {start_set} | {start} | {total - len(ended)}/{total} | {ends} | "
                     f"{statistics.median(steps):g} ({min(steps)}–{max(steps)}) |")
    return lines


def failure_site(episode: EvaluationEpisode) -> str:
    """What a failed episode hit, or how and where it ended; "" for an evaluation from before they were kept."""
    if episode.hit:
        return episode.hit
    return f"{episode.end} on {episode.end_place}" if episode.end_place else ""


def failures_by_site(episodes: Sequence[EvaluationEpisode], policy: str = "greedy") -> list[str]:
    """Where a policy's failed episodes ended, most first: one place of the map can hold the failures of
    several starts (the grid's: one parked car, passed from three test starts)."""
    failed = [episode for episode in episodes if episode.policy == policy and not episode.collision_free]
    by_site: dict[str, list[EvaluationEpisode]] = {}
    for episode in failed:
        by_site.setdefault(failure_site(episode), []).append(episode)
    if not failed or "" in by_site:
        return []
    lines = [f"What the {policy} policy hit, or where it left the road or stalled:", "",
             "| Where | Episodes (train / test) | Starts | Failed at step: median (range) |", "|---|---:|---|---:|"]
    for site, ended in sorted(by_site.items(), key=lambda item: (-len(item[1]), item[0])):
        sets = " / ".join(str(sum(episode.start_set == name for episode in ended)) for name in ("train", "test"))
        starts = "; ".join(f"{name} " + ", ".join(str(index) for index in sorted(
            {episode.start_index for episode in ended if episode.start_set == name}))
            for name in ("train", "test") if any(episode.start_set == name for episode in ended))
        steps = [episode.length for episode in ended]
        lines.append(f"| {site} | {len(ended)} ({sets}) | {starts} | "
                     f"{statistics.median(steps):g} ({min(steps)}–{max(steps)}) |")
    return lines


def evaluation_markdown(summaries: Sequence[SetSummary], edges: Sequence[float], facts: dict[str, str],
                        trials: int, confidence: float = 0.95, episodes: Sequence[EvaluationEpisode] = ()) -> str:
    lines = ["# Evaluation", ""]
    lines += [f"- {name}: {value}" for name, value in facts.items()]
    lines += ["", markdown_table(summaries, edges, confidence), ""]
    note = greedy_variety_note(summaries, trials)
    if note:
        lines += [note, ""]
    for failures in (failures_by_start(episodes), failures_by_site(episodes)):
        if failures:
            lines += [*failures, ""]
    lines += ["Columns:", ""]
    lines += [f"- **{name}**: {meaning}" for name, meaning in COLUMN_LEGEND]
    return "\n".join(lines) + "\n"


def write_evaluation(out_dir: Path, episodes: Sequence[EvaluationEpisode], summaries: Sequence[SetSummary],
                     edges: Sequence[float], facts: dict[str, str], trials: int, config_toml: str,
                     confidence: float = 0.95) -> list[Path]:
    """Writes the five files (the config the evaluation ran with last); returns their paths."""
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = [out_dir / EPISODES_CSV, out_dir / SUMMARY_CSV, out_dir / SUMMARY_MD, out_dir / FACTS_JSON,
             out_dir / CONFIG_TOML]
    write_episodes_csv(paths[0], episodes, edges)
    write_summary_csv(paths[1], summaries, edges)
    paths[2].write_text(evaluation_markdown(summaries, edges, facts, trials, confidence, episodes))
    paths[3].write_text(json.dumps(facts, indent=1) + "\n")
    paths[4].write_text(config_toml)
    return paths


def read_facts(out_dir: Path) -> dict[str, str]:
    """The facts an evaluation wrote, or {} for one written before they were kept."""
    try:
        facts = json.loads((out_dir / FACTS_JSON).read_text())
    except (OSError, ValueError):
        return {}
    return facts if isinstance(facts, dict) else {}


def _percent(share: float) -> str:
    return f"{100 * share:.2f}%"
