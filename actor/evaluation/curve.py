"""Greedy learning curves: every policy a run kept, on the paper's protocol, into one CSV, a figure and
the time to drive.

The learner keeps its online weights every learner.keep_every updates (or keep_every_s seconds)
in <run>/policies/ (KeptPolicy, common/checkpoint.py). `evaluate --curve <run>` runs the greedy
policy of each kept file from every start of both start sets, CURVE_TRIALS trials per start
unless the config says otherwise, and writes one row per kept policy and start set: where the
run stood (updates, env steps, wall time, the CPU it trained on), the priority the evaluation
ran at, and the columns of evaluate's summary.csv with their intervals. A policy already in the
CSV is not run again, so the command can follow a run that goes on; a damaged file is logged and
skipped. The milestones (the time to drive) are read from the rows.
"""

from __future__ import annotations

import argparse
import csv
import json
import logging
import os
import sys
from pathlib import Path
from typing import Callable, Sequence

from actor.evaluation import EvaluationError
from actor.evaluation.protocol import evaluate
from actor.evaluation.sources import check_weights, checkpoint_config
from actor.evaluation.workers import torch_threads_per_worker
from actor.evaluation.curve_figure import plot_curve
from common.analysis.stats import SetSummary
from common.analysis.tables import COVERAGE_COLUMNS, summary_columns
from common.checkpoint import CheckpointError, KeptPolicy
from common.cpu_capability import cpu_model
from common.config import Config
from common.config_values import load_config, to_dict
from common.eta import Eta, clock_time
from common.schema.fields import ConfigError
from common.presets import GRID_SHADOWS_FROM
from common.run_dir import POLICY_KINDS, RunDir

CURVE_TRIALS = 5  # trials per start: a curve evaluates many policies, so fewer than a table's 30
DRIVE_LENGTH = 1000.0  # steps: a greedy test mean length this long is driving
CURVE_CSV, CURVE_PNG = "curve.csv", "curve.png"
SUMMARY_JSON, SUMMARY_MD = "curve_summary.json", "curve_summary.md"
# name, column, threshold, held, what it means: the first kept policy whose test row reaches the threshold
# (held: and every later one's too; greedy curves swing by hundreds of steps between neighbouring policies,
# so a first crossing at K = 5 can be luck)
MILESTONES = (("drive", "mean_length", DRIVE_LENGTH, False, "greedy test mean length >= 1,000 steps"),
              ("drive_held", "mean_length", DRIVE_LENGTH, True,
               "greedy test mean length >= 1,000 steps at every kept policy from there on"),
              ("half_cfr", "cfr", 0.5, False, "greedy test CFR >= 50%"))

# The late curve: the kept policies from here on, where every run of the first grid had driven; how far the
# greedy policy swings there is what the shadow kinds (learner.keep_target, ema_updates) are read on.
LATE_FROM = GRID_SHADOWS_FROM
KEEPING = {"online": "learner.keep_every or learner.keep_every_s", "target": "learner.keep_target",
           "ema": "learner.ema_updates", "mean": "deploy/tools/average_policies.py"}

log = logging.getLogger("evaluate")


def curve_config(saved: dict, args: argparse.Namespace) -> Config:
    """A kept policy's config with CURVE_TRIALS trials per start, and with --follow one torch thread per
    worker (evaluation.torch_threads: beside a run a second thread waits on a busy core), then --config FILE
    and the flags given."""
    evaluation = saved.get("evaluation")
    beside_a_run = {"torch_threads": 1} if getattr(args, "follow", None) is not None else {}
    trials = ({"evaluation": {**evaluation, "episodes_per_start": CURVE_TRIALS, **beside_a_run}}
              if isinstance(evaluation, dict) else {})
    return checkpoint_config({**saved, **trials}, args)


def crowding_warning(learner_threads: int, workers: int, worker_threads: int, cores: int) -> str | None:
    """What to say when a learner's torch threads (learner.torch_threads; 0: torch's default, every core) and a
    follower's workers x threads together exceed the cores, else None. An update runs its threads in step, so
    one of them waiting on a core a follower's worker holds stalls the whole update (a forward pass on 2 threads
    ran 8 times slower than on 1 beside busy cores)."""
    learner = learner_threads or cores
    follower = workers * worker_threads
    if learner + follower <= cores:
        return None
    origin = f"learner.torch_threads {learner_threads}" if learner_threads else "learner.torch_threads 0: every core"
    room = cores - follower
    advice = (f"run the learner with --learner.torch_threads {room}" if room >= 1 else
              "give the follower fewer workers or threads (--evaluation.workers, --evaluation.torch_threads)")
    return (f"the run's learner takes {learner} torch thread(s) ({origin}) and this follower {workers} worker(s) x "
            f"{worker_threads} thread(s): {learner} + {follower} > {cores} cores, so the learner's updates will wait "
            f"on the follower; {advice}, or evaluate the curve after training (without --follow)")


def warn_if_crowding(run: RunDir, args: argparse.Namespace, cores: int | None = None) -> str | None:
    """--follow: logs crowding_warning for the learner's threads in the run's config.toml and this follower's
    (curve_config of that config: the flags given, one thread per worker unless told); returns the line."""
    try:
        config = load_config(toml_path=run.config)
    except ConfigError as error:
        log.warning("cannot weigh the learner's torch threads against this follower's: %s", error)
        return None
    evaluation = curve_config(to_dict(config), args).evaluation
    warning = crowding_warning(config.learner.torch_threads, evaluation.workers,
                               torch_threads_per_worker(evaluation, evaluation.workers),
                               os.cpu_count() if cores is None else cores)
    if warning is not None:
        log.warning("%s", warning)
    return warning


def evaluate_curve(run: RunDir, out_dir: Path, start_sets: Sequence[str], configure: Callable[[dict], Config],
                   nice: int, show_status: bool = True, from_updates: int = 0, every: int = 1,
                   to_updates: int | None = None, kinds: Sequence[str] = ("online",)) -> list[dict] | None:
    """Evaluates the kept policies of `kinds` (those kept from `from_updates` to `to_updates`, at multiples of
    `every`) the CSV lacks, on the start sets it lacks them on (a curve of the test set, rerun with train,test,
    adds the train rows), writing it after each; returns all its rows (of every kind), or None when nothing
    was added (nothing new, or every new file skipped)."""
    kept = []
    for kind in kinds:
        found = run.kept_policies(kind)
        if not found:
            raise EvaluationError(f"no kept {kind} policies in {run.policy_folder(kind)}/ (the learner keeps them "
                                  f"with {KEEPING[kind]})")
        kept += [(updates, kind, file) for updates, file in curve_policies(found, from_updates, every, to_updates)]
    if not kept:
        until = "" if to_updates is None else f", --to-updates {to_updates:,d}"
        raise EvaluationError(f"--from-updates {from_updates:,d}{until}, --every {every:,d}: no policy in "
                              f"{run.policies}/ was kept in that span at such a multiple")
    path = out_dir / CURVE_CSV
    rows = read_curve(path, kind=None)
    done = {(int(row["updates"]), row["start_set"], row["kind"]) for row in rows}
    todo = [(updates, kind, file, missing) for updates, kind, file in sorted(kept)
            if (missing := [name for name in start_sets if (updates, name, kind) not in done])]
    if not todo:
        print(f"curve: nothing new: all {len(kept)} kept policies are in {path}", file=sys.stderr)
        return None
    eta, added = Eta(len(todo)), 0
    eta.update(0)
    for number, (updates, kind, file, missing) in enumerate(todo, 1):
        new = policy_rows(file, updates, missing, configure, nice, show_status, kind)
        if new:
            rows = write_curve(path, rows + new)
            added += 1
        eta.update(number)
        print(f"curve: {number}/{len(todo)} kept policies, ETA {eta.text()}: {file.name} {headline(new)}",
              file=sys.stderr, flush=True)
    if not added:
        print(f"curve: every new kept policy was skipped; {path} is unchanged", file=sys.stderr)
        return None
    return rows


def curve_policies(kept: Sequence[tuple[int, Path]], from_updates: int = 0, every: int = 1,
                   to_updates: int | None = None) -> list[tuple[int, Path]]:
    """Of a run's kept policies, those a curve reads: kept from `from_updates` to `to_updates` (None: no end),
    at multiples of `every`."""
    return [(updates, file) for updates, file in kept if updates >= from_updates and updates % every == 0
            and (to_updates is None or updates <= to_updates)]


def policy_rows(file: Path, updates: int, start_sets: Sequence[str], configure: Callable[[dict], Config],
                nice: int, show_status: bool, kind: str = "online") -> list[dict]:
    """The curve's rows of one kept policy; none, with a log line, when the file cannot be used."""
    try:
        policy = KeptPolicy.load(file)
        if policy.updates != updates:
            raise CheckpointError(f"its name says update {updates}, it holds update {policy.updates}")
        if policy.kind != kind:
            raise CheckpointError(f"it lies with the {kind} policies but holds a {policy.kind} one")
        config = configure(policy.config)
        weights = policy.weights()
        check_weights(config, weights)
    except (CheckpointError, ConfigError, EvaluationError) as error:
        log.warning("skipped %s: %s", file, error)
        return []
    _, summaries = evaluate(config, weights, ["greedy"], start_sets, show_status)
    return [curve_row(policy, summary, config.evaluation.reward_bins, nice) for summary in summaries]


def curve_row(policy: KeptPolicy, summary: SetSummary, edges: Sequence[float], nice: int) -> dict:
    return {"updates": policy.updates, "kind": policy.kind, "env_steps": policy.env_steps,
            "wall_s": round(policy.wall_s, 3), "kept_file": policy.path.name, "trained_on": policy.cpu,
            "trained_precision": policy.precision, "nice": nice,
            **summary_columns(summary, edges)}


def headline(rows: list[dict]) -> str:
    """'test: mean length 41.2, CFR 0.0%; train: ...' of one policy's rows, or 'skipped'."""
    return "; ".join(f"{row['start_set']}: mean length {float(row['mean_length']):,.1f}, "
                     f"CFR {100 * float(row['cfr']):.1f}%" for row in rows) or "skipped"


# --- the CSV ----------------------------------------------------------------------------------------------

def read_curve(path: Path, kind: str | None = "online") -> list[dict]:
    """The rows of a curve CSV of one policy kind (None: of all), [] when there is none yet. A curve written
    before the coverage columns reads them as "nan" (not measured), before the learner's precision column as
    "" (not recorded), and before the kinds as online, so that a rerun can add rows with them to it."""
    if not path.exists():
        return []
    try:
        with path.open(newline="") as handle:
            rows = list(csv.DictReader(handle))
        for row in rows:  # what the milestones and the study read: a damaged cell is this error, not a crash later
            int(row["updates"]), int(row["env_steps"])
            float(row["wall_s"]), float(row["mean_length"]), float(row["cfr"])
    except (OSError, csv.Error, KeyError, TypeError, ValueError) as error:
        raise EvaluationError(f"{path} is not a curve of evaluate --curve ({type(error).__name__}: {error}); "
                              "move it away or give another --out") from None
    rows = [{"trained_precision": "", "kind": "online", **row,
             **{column: "nan" for column in COVERAGE_COLUMNS if column not in row}} for row in rows]
    strange = sorted({row["kind"] for row in rows} - set(POLICY_KINDS))
    if strange:
        raise EvaluationError(f"{path}: kind {strange[0]!r} is not one of {', '.join(POLICY_KINDS)}; move it away "
                              "or give another --out")
    return rows if kind is None else of_kind(rows, kind)


def of_kind(rows: Sequence[dict], kind: str = "online") -> list[dict]:
    """A curve's rows of one policy kind (rows without a kind are online ones)."""
    return [row for row in rows if row.get("kind", "online") == kind]


def write_curve(path: Path, rows: list[dict]) -> list[dict]:
    """All rows, by updates, atomically: an interruption leaves the previous file whole. The columns are in
    the order of the last row, the newest evaluation's. Returns the rows as the file holds them (strings, as
    read_curve gives them), so that rows just evaluated and rows read back compare alike."""
    columns = list(rows[-1])
    if any(set(row) != set(columns) for row in rows):
        raise EvaluationError(f"{path} has other columns than this evaluation writes (other reward bins?); "
                              "give another --out")
    # by updates, the kinds in POLICY_KINDS' order, train then test
    rows = sorted(rows, key=lambda row: (int(row["updates"]), POLICY_KINDS.index(row["kind"]),
                                         row["start_set"] != "train"))
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    with temporary.open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=columns)
        writer.writeheader()
        writer.writerows(rows)
    os.replace(temporary, path)
    return [{key: "" if value is None else str(value) for key, value in row.items()} for row in rows]


# --- the time to drive ---------------------------------------------------------------------------------------

def first_reaching(rows: Sequence[dict], column: str, threshold: float, start_set: str = "test",
                   held: bool = False) -> dict | None:
    """Where the run stood at the first kept policy whose `column` on `start_set` reached `threshold`;
    held: the first from which every later one's did too (None while the last one reads below)."""
    found = None
    for row in sorted((row for row in rows if row["start_set"] == start_set), key=lambda row: int(row["updates"])):
        if float(row[column]) < threshold:
            found = None
        elif found is None:
            found = row
            if not held:
                break
    if found is None:
        return None
    return {"updates": int(found["updates"]), "env_steps": int(found["env_steps"]), "wall_s": float(found["wall_s"]),
            "trained_on": trained_with([found]), "kept_file": found["kept_file"], column: float(found[column])}


def trained_with(rows: Sequence[dict]) -> str:
    """The learner's CPU and precision by the kept policies of a curve's rows, a span each where they changed
    (learner.precision auto is bfloat16 on one CPU and float32 on another): "AMD EPYC, float32", or
    "AMD EPYC, float32 to 16,000 updates; Intel Xeon, bfloat16 from 18,000"."""
    by_updates = {int(row["updates"]): row for row in reversed(rows)}  # one row per policy: the first
    spans: list[tuple[str, int, int]] = []  # (machine, first updates, last updates)
    for updates, row in sorted(by_updates.items()):
        machine = f"{row['trained_on']}, {row.get('trained_precision') or 'precision not recorded'}"
        first = spans.pop()[1] if spans and spans[-1][0] == machine else updates
        spans.append((machine, first, updates))
    if not spans:
        return ""
    first_span = f"{spans[0][0]} to {spans[0][2]:,d} updates" if len(spans) > 1 else spans[0][0]
    return "; ".join([first_span] + [f"{machine} from {first:,d}" for machine, first, _ in spans[1:]])


def chosen_on_train(rows: Sequence[dict]) -> dict | None:
    """The kept policy to ship, chosen on the training starts alone (highest greedy train CFR, then mean
    length, then the later policy) among the kept policies evaluated on them (all, or a run's last ones:
    `evaluate --curve --from-updates`), with its train and test readings and which policies it was chosen
    among: choosing on the test starts would make its test reading the best of many draws, biased upwards.
    None when no policy was evaluated on the training starts."""
    train = [row for row in rows if row["start_set"] == "train"]
    if not train:
        return None
    best = max(train, key=lambda row: (float(row["cfr"]), float(row["mean_length"]), int(row["updates"])))
    # rows read back from the CSV hold strings, rows just evaluated numbers
    test = next((row for row in rows if row["start_set"] == "test" and int(row["updates"]) == int(best["updates"])),
                None)
    among = sorted(int(row["updates"]) for row in train)
    return {"updates": int(best["updates"]), "kept_file": best["kept_file"],
            **{f"{name}_{column}": float(row[column]) if row is not None else None
               for name, row in (("train", best), ("test", test)) for column in ("cfr", "mean_length")},
            "among": len(among), "of": len({int(row["updates"]) for row in rows}), "among_first": among[0],
            "among_last": among[-1]}


def curve_summary(rows: Sequence[dict], evaluated_on: str | None = None) -> dict:
    """The milestones of a curve's rows, the policy chosen on the training starts, and what they were
    measured from (evaluated_on: the CPU of the evaluation, this one's unless given)."""
    return {
        "chosen_on_train": chosen_on_train(rows),
        "policies": len({row["updates"] for row in rows}),
        "last_updates": max(int(row["updates"]) for row in rows),
        "test_set": any(row["start_set"] == "test" for row in rows),
        "nice": sorted({int(row["nice"]) for row in rows}),
        "evaluated_on": evaluated_on if evaluated_on is not None else cpu_model(),
        **{name: {"criterion": criterion, "reached": first_reaching(rows, column, threshold, held=held)}
           for name, column, threshold, held, criterion in MILESTONES},
    }


def late_curves(rows: Sequence[dict], from_updates: int = LATE_FROM) -> dict[str, dict]:
    """Per policy kind that has test rows kept at `from_updates` or later: how many, the mean and the least of
    their greedy test CFR, and their mean test length."""
    late = {}
    for kind in POLICY_KINDS:
        test = [row for row in of_kind(rows, kind) if row["start_set"] == "test" and int(row["updates"]) >= from_updates]
        if test:
            cfr = [float(row["cfr"]) for row in test]
            late[kind] = {"from_updates": from_updates, "policies": len(test), "test_cfr_mean": sum(cfr) / len(cfr),
                          "test_cfr_min": min(cfr),
                          "test_mean_length_mean": sum(float(row["mean_length"]) for row in test) / len(test)}
    return late


def summary_lines(summary: dict) -> list[str]:
    lines = []
    for name, *_ in MILESTONES:
        if name not in summary:  # a summary written before this milestone
            continue
        criterion, reached = summary[name]["criterion"], summary[name]["reached"]
        if reached is not None:
            lines.append(f"first {criterion}: update {reached['updates']:,d}, {reached['env_steps']:,d} env steps, "
                         f"{clock_time(reached['wall_s'])} of wall time, trained on {reached['trained_on']}")
        elif not summary["test_set"]:
            lines.append(f"first {criterion}: the test set was not evaluated")
        else:
            lines.append(f"first {criterion}: not reached in {summary['policies']} kept policies "
                         f"(up to update {summary['last_updates']:,d})")
    chosen = summary.get("chosen_on_train")
    if chosen is None and "chosen_on_train" in summary:
        lines.append("chosen on the training starts: no kept policy was evaluated on them (--sets train,test)")
    if chosen is not None:
        test = ("not evaluated on the test starts" if chosen["test_cfr"] is None else
                f"test CFR {100 * chosen['test_cfr']:.0f}%, mean length {chosen['test_mean_length']:,.0f}")
        among = ("" if "among" not in chosen or chosen["among"] == chosen["of"] else
                 f" among the {chosen['among']} of {chosen['of']} kept policies evaluated on them "
                 f"({chosen['among_first']:,d}-{chosen['among_last']:,d} updates)")
        lines.append(f"chosen on the training starts{among} (highest train CFR, then mean length): update "
                     f"{chosen['updates']:,d} ({chosen['kept_file']}): train CFR {100 * chosen['train_cfr']:.0f}%, "
                     f"mean length {chosen['train_mean_length']:,.0f}; {test}")
    for kind, late in summary.get("late_curve", {}).items():
        lines.append(f"late curve of the {kind} policies ({late['policies']} kept from {late['from_updates']:,d} "
                     f"updates): test CFR {100 * late['test_cfr_mean']:.1f}% on average, "
                     f"{100 * late['test_cfr_min']:.0f}% at the least; mean length "
                     f"{late['test_mean_length_mean']:,.0f}")
    nice = ", ".join(str(value) for value in summary["nice"])
    lines.append(f"evaluated on {summary['evaluated_on']} at nice {nice}")
    return lines


def previous_evaluation_cpu(path: Path) -> str:
    try:
        named = json.loads(path.read_text()).get("evaluated_on")
    except (OSError, ValueError, AttributeError):
        named = None
    return named if isinstance(named, str) else "not recorded"


def write_summary(out_dir: Path, summary: dict, run_name: str) -> list[Path]:
    paths = [out_dir / SUMMARY_JSON, out_dir / SUMMARY_MD]
    paths[0].write_text(json.dumps(summary, indent=1) + "\n")
    body = "\n".join(f"- {line}" for line in summary_lines(summary))
    paths[1].write_text(f"# Greedy learning curve of {run_name}: time to drive\n\n{body}\n")
    return paths


def write_outputs(out_dir: Path, rows: list[dict], run_name: str, evaluated_now: bool = True) -> tuple[dict, list[Path]]:
    """The figure and the summary of the curve's online rows, with the late curve of every kind it holds.
    Redrawn without evaluating (evaluated_now False), the summary keeps the evaluation CPU it named: this
    machine may not be the one that evaluated."""
    figure, online = out_dir / CURVE_PNG, of_kind(rows)
    if not online:
        raise EvaluationError(f"{out_dir / CURVE_CSV} has no rows of the online policies: evaluate them first "
                              "(--kinds online), the summary and figure are theirs")
    plot_curve(online, figure, f"greedy learning curve of {run_name} (bands: intervals over the trials)")
    summary = curve_summary(online, None if evaluated_now else previous_evaluation_cpu(out_dir / SUMMARY_JSON))
    summary["late_curve"] = late_curves(rows)
    return summary, [out_dir / CURVE_CSV, figure, *write_summary(out_dir, summary, run_name)]
