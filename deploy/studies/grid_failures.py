"""Where the grid's runs failed (the report's sections on it; runs are grid_report.GridRun):

- each run's chosen policy's test CFR per test start, with per start the mean over runs and the runs below half;
- what its failed test episodes hit, pooled by place (common/analysis/tables.failure_site), for evaluations that
  recorded it (or older ones replayed by deploy/tools/failure_sites.py --write);
- the prediction written down before the grid's seed-2 runs (docs/results/grid.md, 2026-12-06), read on those
  runs by a fixed rule, so that a pattern found by looking at seeds 0 and 1 is tested on runs that did not
  suggest it.

The pattern: test starts 1, 2 and 9 hold most failures, and the runs that fail them explore by softmax draws.
The prediction: on those starts, the seed-2 runs of Softmax, MBE and VDBE-Softmax read a lower CFR than the
seed-2 runs of constant epsilon, decreasing epsilon and VDBE (buffer 1,000, the paper's learner).

The rule: a run's score is its chosen policy's CFR over the three starts (the mean of its per-start CFR). With all
six runs in, the prediction is

* "confirmed" when every softmax-family run scores below every other run: the one-sided Mann-Whitney p is then
  1 / C(6, 3) = 0.05, the least three runs against three can give;
* "holds in the mean" when the softmax family's mean score is below the other group's but the runs overlap;
* "refuted" otherwise.

Until then it is "pending", with the runs in so far shown.
"""

from __future__ import annotations

from collections import Counter
from typing import Sequence

import numpy as np

from common.analysis import across_seeds
from common.analysis.tables import failure_site

HARD_STARTS = (1, 2, 9)
SEED = 2
CELL = (1000, "paper")
SOFTMAX_FAMILY = ("softmax", "max_boltzmann", "vdbe_softmax")
UNIFORM = ("constant", "decreasing", "vdbe")
CONFIRMED, IN_THE_MEAN, REFUTED, PENDING = "confirmed", "holds in the mean", "refuted", "pending"


def start_lines(runs: Sequence) -> list[str]:
    """Each run's chosen policy's test CFR per start, and per start the mean over runs and the runs below half:
    whether a run's CFR is spread over the starts or lost on a few."""
    starts = min((len(item.start_cfr) for item in runs), default=0)
    header = " | ".join(str(start) for start in range(starts))
    lines = ["Test CFR of each run's chosen policy from each test start (K trials each).", "",
             f"| Run | {header} |", "|---|" + "---:|" * starts]
    lines += [f"| {item.run.name} | " + " | ".join(f"{100 * cfr:.0f}%" for cfr in item.start_cfr[:starts]) + " |"
              for item in runs]
    scores = np.vstack([item.start_cfr[:starts] for item in runs]) if runs else np.zeros((0, starts))
    lines.append("| mean over runs | " + " | ".join(f"{100 * value:.0f}%" for value in scores.mean(axis=0)) + " |")
    lines.append("| runs below 50% | " + " | ".join(str(int(count)) for count in (scores < 0.5).sum(axis=0)) + " |")
    return lines


def failed_test_sites(episodes) -> Counter | None:
    """The failed greedy test episodes by place; None when any of them lacks its place (an older evaluation)."""
    failed = [episode for episode in episodes
              if episode.policy == "greedy" and episode.start_set == "test" and not episode.collision_free]
    sites = Counter(failure_site(episode) for episode in failed)
    return None if "" in sites else sites


def site_lines(runs: Sequence) -> list[str]:
    """Per run whose evaluation recorded them: its test failures, the place that holds most, and the others."""
    recorded = [item for item in runs if item.test_sites is not None]
    lines = ["The failed test episodes of each run's chosen policy by what they hit, or where they left the road "
             "or stalled (deploy/tools/failure_sites.py; evaluations record it from commit d1de71a on, older ones "
             "are replayed with their policy where it is kept, checked by action digest).", ""]
    if not recorded:
        return lines + ["No run's evaluation records where its failures happened yet."]
    lines += ["| Run | Test failures | Where most happened | There | Elsewhere |", "|---|---:|---|---:|---|"]
    for item in recorded:
        sites = item.test_sites.most_common()
        total = sum(item.test_sites.values())
        if not sites:
            lines.append(f"| {item.run.name} | 0 | – | – | – |")
            continue
        (place, count), others = sites[0], sites[1:]
        elsewhere = "; ".join(f"{other} ({number})" for other, number in others) or "–"
        lines.append(f"| {item.run.name} | {total} | {place} | {count} | {elsewhere} |")
    missing = [item.run.name for item in runs if item.test_sites is None]
    if missing:
        lines += ["", f"Not recorded: {', '.join(missing)}."]
    return lines


def hard_start_score(start_cfr: np.ndarray) -> float:
    """A run's CFR over the hard starts."""
    return float(np.mean([start_cfr[start] for start in HARD_STARTS]))


def prediction_scores(runs: Sequence) -> dict[str, float | None]:
    """Each predicted run's score by strategy, None where its run is not in (runs: grid_report.GridRun)."""
    scores: dict[str, float | None] = dict.fromkeys(SOFTMAX_FAMILY + UNIFORM)
    for item in runs:
        if item.cell == CELL and item.run.seed == SEED and item.run.strategy in scores:
            scores[item.run.strategy] = hard_start_score(item.start_cfr)
    return scores


def prediction_reading(scores: dict[str, float | None]) -> tuple[str, float | None]:
    """(reading, one-sided Mann-Whitney p that the softmax family scores lower) by the module's rule."""
    if any(value is None for value in scores.values()):
        return PENDING, None
    family = np.array([scores[name] for name in SOFTMAX_FAMILY])
    uniform = np.array([scores[name] for name in UNIFORM])
    p_value = across_seeds.mann_whitney_p(uniform, family)
    if family.max() < uniform.min():
        return CONFIRMED, p_value
    return (IN_THE_MEAN if family.mean() < uniform.mean() else REFUTED), p_value


def prediction_lines(runs: Sequence) -> list[str]:
    scores = prediction_scores(runs)
    reading, p_value = prediction_reading(scores)
    starts = ", ".join(map(str, HARD_STARTS))
    lines = [f"Stated before the seed-{SEED} runs (docs/results/grid.md): on test starts {starts}, the seed-{SEED} "
             "runs of Softmax, MBE and VDBE-Softmax read a lower CFR than those of constant epsilon, decreasing "
             "epsilon and VDBE. The rule (deploy/studies/grid_failures.py): confirmed when every softmax-family "
             "run reads below every other (one-sided Mann-Whitney p = 0.05, the least 3 runs against 3 give); "
             "holds in the mean when only the group means are so ordered; refuted otherwise.", "",
             f"| Group | Strategy | CFR on starts {starts} |", "|---|---|---:|"]
    for group, names in (("softmax family", SOFTMAX_FAMILY), ("uniform draws", UNIFORM)):
        for name in names:
            value = scores[name]
            lines.append(f"| {group} | {name} | {'not run yet' if value is None else f'{100 * value:.0f}%'} |")
    verdict = f"**{reading}**" + ("" if p_value is None else f" (p = {p_value:.2f})")
    done = sum(value is not None for value in scores.values())
    return lines + ["", f"Reading with {done} of {len(scores)} runs: {verdict}."]
