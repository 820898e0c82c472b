"""Mutation testing of the math modules: does the suite fail when the code is changed a little?

mutmut (PyPI; this script was written against 3.8.1: `.venv/bin/pip install mutmut==3.8.1`, not a
dependency of the project) changes one operator, constant or argument at a time, and runs the
tests that reach the changed function. A mutant that no test fails "survived": either a test is
missing, or the change is equivalent (the code computes the same), and results/mutation/report.md
says which, for each.

Each target runs on its own copy of the working tree (the tracked files and the untracked ones git
does not ignore, results/ left out) in a scratch folder, with a setup.cfg of its own, so that the
project's pyproject.toml carries no mutmut settings and the checkout is never written to:

    pacing        common/pacing.py              tests/test_rate_limiter.py tests/test_run_end.py
    rate_limiter  replay/rate_limiter.py        tests/test_rate_limiter.py tests/test_run_end.py
    exploration   common/exploration/*.py       tests/test_exploration.py tests/test_strategies.py
    update        learner/loss.py and update_path.py (the loss math; --all-update for every function of the learner's step)
                                                tests/test_update.py tests/test_update_by_reference.py
                                                (and precision_from_timings' test)

It is a benchmark, not part of CI: minutes per target on two cores (docs/benchmarks.md). Every run
is at `nice -n 19` with one torch thread, so that it takes only the CPU nobody else wants; the
per-mutant timeout is in CPU seconds (mutmut's SIGXCPU limit), so a busy machine slows the run down
without turning mutants into false timeouts.

    .venv/bin/python deploy/bench/mutation.py                       # all four targets
    .venv/bin/python deploy/bench/mutation.py pacing rate_limiter   # some of them
    .venv/bin/python deploy/bench/mutation.py update --budget 1800  # stop after 30 min
    .venv/bin/python deploy/bench/mutation.py update --resume       # go on where the budget stopped it
    .venv/bin/python deploy/bench/mutation.py exploration --recheck # the survivors against today's tests
    .venv/bin/python deploy/bench/mutation.py --table               # the report's table

Writes results/mutation/<target>.json (every mutant's verdict, every survivor's diff) and
<target>.after.json (--recheck), and prints a summary; results/mutation/report.md is written by
hand from them (which survivor is equivalent and why).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import signal
import subprocess
import sys
import time
from collections import Counter
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
MUTMUT_VERSION = "3.8.1"

# The packages mutmut copies into its mutants/ folder: all four, so that a test importing any of
# them gets the copy there (mutmut takes the checkout itself off sys.path), mutated or not.
PACKAGES = ("common", "learner", "replay", "actor")

# learner/loss.py's math and learner/update_path.py's rule, the targets, the masked loss, the burn-in, the start state, the
# one-pass and trace-pass losses, and the rule that picks a precision from timings. Left out by
# default (--all-update puts them back): the learner's methods (its split trace pass, exploration
# terms, soft update, precision and path switches), the checks and staging of a batch, checkpoints
# and the timing loops; their tests run whole updates, so every surviving mutant there costs
# minutes on two shared cores.
UPDATE_MATH = (
    "x_double_q_targets", "x_masked_squared_error", "x_taken_action_values", "x_start_state",
    "x_burn_in_steps", "x_burnt_in_forward", "x_one_pass_loss", "x_one_pass_terms", "x_trace_pass_loss",
    "x_precision_from_timings",
)


@dataclass(frozen=True)
class Target:
    name: str
    mutate: tuple[str, ...]  # glob patterns of the files to mutate (mutmut's only_mutate)
    tests: tuple[str, ...]  # the test files that cover them
    functions: tuple[str, ...] = ()  # mutmut's mangled function names, to mutate only those; () = all
    deselect: tuple[str, ...] = ()  # slow tests left out: every surviving mutant would pay for them

    def mutant_globs(self, module: str) -> list[str]:
        return [f"{module}.{f}__mutmut_*" for f in self.functions]


TARGETS = {
    "pacing": Target("pacing", ("common/pacing.py",), ("tests/test_rate_limiter.py", "tests/test_run_end.py")),
    "rate_limiter": Target("rate_limiter", ("replay/rate_limiter.py",),
                           ("tests/test_rate_limiter.py", "tests/test_run_end.py")),
    "exploration": Target("exploration", ("common/exploration/*",),
                          ("tests/test_exploration.py", "tests/test_strategies.py")),
    "update": Target("update", ("learner/loss.py", "learner/update_path.py", "learner/update.py", "learner/trace_batch.py"),
                     ("tests/test_update.py", "tests/test_update_by_reference.py",
                      # precision_from_timings' own test; the rest of that file times real updates
                      "tests/test_learner_precision.py::"
                      "test_the_precision_decision_takes_the_best_of_each_candidates_timings"),
                     UPDATE_MATH,
                     # 24 s and 17 s of the file's 100: learning a synthetic task end to end, and the
                     # timing that picks a path; the formulas have tests of their own, by hand
                     ("tests/test_update.py::test_learns_which_action_pays_on_a_synthetic_task",
                      "tests/test_update.py::test_auto_times_every_path_once_per_process_and_changes_nothing")),
}

# mutmut's exit codes per mutant (mutmut/stats.py), folded into the report's columns.
STATUS = {1: "killed", 3: "killed", 0: "survived", 5: "no tests", 33: "no tests", 34: "skipped",
          36: "timeout", 24: "timeout", -24: "timeout", 152: "timeout", 255: "timeout",
          37: "type check", None: "not checked", -9: "segfault", -11: "segfault"}


def copy_tree(scratch: Path) -> None:
    """The working tree as git sees it (untracked new tests included), results/ left out."""
    listed = subprocess.run(["git", "ls-files", "-co", "--exclude-standard", "-z"], cwd=ROOT, check=True,
                            capture_output=True).stdout.decode().split("\0")
    for name in listed:
        if not name or name.startswith("results/") or not (ROOT / name).is_file():
            continue
        (scratch / name).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(ROOT / name, scratch / name)


def setup_cfg(target: Target, timeout_multiplier: float) -> str:
    lines = ["[mutmut]", "source_paths ="] + [f"    {p}" for p in PACKAGES]
    lines += ["only_mutate ="] + [f"    {p}" for p in target.mutate]
    lines += ["pytest_add_cli_args_test_selection ="] + [f"    {t}" for t in target.tests]
    lines += [f"    --deselect={t}" for t in target.deselect]
    # -p no:cacheprovider: no .pytest_cache; -x: one failing test kills the mutant, stop there
    lines += ["pytest_add_cli_args =", "    -p", "    no:cacheprovider", "    -x", "    -q"]
    # CPU seconds per mutant: (the covering tests' measured time + 1 s) x multiplier x 2
    lines += [f"timeout_multiplier = {timeout_multiplier}", "timeout_constant = 1.0",
              # the fork server keeps torch's threads out of the process every mutant forks from
              "process_isolation = forkserver", "use_git_change_detection = false"]
    return "\n".join(lines) + "\n"


def mutant_results(scratch: Path, target: Target) -> dict[str, dict]:
    """Per mutated file: mutant name -> status, from mutmut's .meta files."""
    by_file = {}
    for meta in sorted((scratch / "mutants").rglob("*.py.meta")):
        source = str(meta.relative_to(scratch / "mutants"))[:-len(".meta")]
        codes = json.loads(meta.read_text())["exit_code_by_key"]
        if target.functions:
            module = source[:-3].replace("/", ".")
            codes = {k: v for k, v in codes.items()
                     if any(k.startswith(f"{module}.{f}__mutmut_") for f in target.functions)}
        by_file[source] = {k: STATUS.get(v, f"exit {v}") for k, v in codes.items()}
    return by_file


def diff_of(scratch: Path, mutant: str) -> str:
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    shown = subprocess.run([mutmut_bin(), "show", mutant], cwd=scratch, env=env, capture_output=True, text=True)
    return "\n".join(line for line in shown.stdout.splitlines()[1:] if line.startswith(("+", "-", "@@"))
                     and not line.startswith(("+++", "---")))


def mutmut_bin() -> str:
    return str(Path(sys.executable).with_name("mutmut"))


def run_target(target: Target, work: Path, out: Path, budget_s: float, children: int,
               timeout_multiplier: float, resume: bool) -> dict:
    scratch = work / target.name
    earlier_s = {"wall_s": 0.0, "cpu_s": 0.0}
    if resume and (scratch / "mutants").is_dir():
        # the same copy, tests included: mutmut keeps its verdicts and tests only the mutants left
        if (out / f"{target.name}.json").exists():
            earlier = json.loads((out / f"{target.name}.json").read_text())
            earlier_s = {key: earlier[key] for key in earlier_s}
    else:
        shutil.rmtree(scratch, ignore_errors=True)
        scratch.mkdir(parents=True)
        copy_tree(scratch)
        (scratch / "setup.cfg").write_text(setup_cfg(target, timeout_multiplier))
    module_globs = []
    if target.functions:
        for pattern in target.mutate:
            module_globs += target.mutant_globs(pattern[:-3].replace("/", "."))
    started = time.monotonic()
    cpu_before = os.times()
    finished, exit_code = run_mutmut(scratch, work / f"{target.name}.log", module_globs, budget_s, children, resume)
    wall = time.monotonic() - started
    cpu_after = os.times()
    by_file = mutant_results(scratch, target)
    counts = {source: dict(Counter(statuses.values())) for source, statuses in by_file.items()}
    survivors = {name: diff_of(scratch, name) for statuses in by_file.values()
                 for name, status in sorted(statuses.items()) if status in ("survived", "timeout", "no tests")}
    report = {
        "target": target.name,
        "mutated": list(target.mutate),
        "functions": list(target.functions),
        "tests": list(target.tests),
        "date": datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        "cpu": cpu_name(),
        "mutmut": MUTMUT_VERSION,
        "exit_code": exit_code,
        "finished": finished,
        "wall_s": round(earlier_s["wall_s"] + wall, 1),
        "cpu_s": round(earlier_s["cpu_s"] + (cpu_after.children_user + cpu_after.children_system)
                       - (cpu_before.children_user + cpu_before.children_system), 1),
        "counts": counts,
        "statuses": by_file,
        "survivors": survivors,
    }
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{target.name}.json").write_text(json.dumps(report, indent=1, ensure_ascii=False) + "\n")
    return report


def recheck_target(target: Target, work: Path, out: Path, budget_s: float, children: int) -> dict:
    """The survivors and the mutants no test reached in the last run, against today's tests:
    today's test files go into the run's copy and mutmut runs those mutants again (it collects the new
    tests' coverage first, then runs only the tests that reach each mutant). Writes <target>.after.json;
    the full run's kills stand (tests are added between runs, not changed), and so do an earlier
    recheck's."""
    scratch = work / target.name
    before = json.loads((out / f"{target.name}.json").read_text())
    for test in {t.split("::")[0] for t in target.tests}:
        shutil.copy2(ROOT / test, scratch / test)  # mutmut copies tests/ into its folder at each run
    status = {m: s for statuses in before["statuses"].values() for m, s in statuses.items()}
    earlier = out / f"{target.name}.after.json"
    rechecked = ({m: s for m, s in json.loads(earlier.read_text())["rechecked"].items() if s == "killed"}
                 if earlier.exists() else {})
    # a timeout is caught already (a test hangs on it), and each costs its whole CPU limit again
    names = sorted(m for m, s in status.items() if s in ("survived", "no tests") and m not in rechecked)
    started = time.monotonic()
    finished = True
    if names:
        finished, _ = run_mutmut(scratch, work / f"{target.name}.recheck.log", names, budget_s, children, False)
        now = {m: s for statuses in mutant_results(scratch, target).values() for m, s in statuses.items()}
        rechecked.update({m: now[m] for m in names})
    after = {"target": target.name, "date": datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
             "cpu": cpu_name(), "wall_s": round(time.monotonic() - started, 1), "finished": finished,
             "before": status, "rechecked": rechecked}
    (out / f"{target.name}.after.json").write_text(json.dumps(after, indent=1, ensure_ascii=False) + "\n")
    return after


def run_mutmut(scratch: Path, log_path: Path, names: list[str], budget_s: float, children: int,
               append: bool) -> tuple[bool, int]:
    """`mutmut run` in the copy, at nice 19, stopped like Ctrl-C at the budget: (finished, exit code)."""
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "MUTANT_UNDER_TEST")}
    # one thread per mutant: two cores, shared, and the tests' batches are small
    env.update(OMP_NUM_THREADS="1", MKL_NUM_THREADS="1", PYTHONHASHSEED="0")
    command = ["nice", "-n", "19", mutmut_bin(), "run", "--max-children", str(children), *names]
    with log_path.open("a" if append else "w") as log:
        process = subprocess.Popen(command, cwd=scratch, env=env, stdout=log, stderr=subprocess.STDOUT,
                                   start_new_session=True)
        try:
            process.wait(timeout=budget_s)
            return True, process.returncode
        except subprocess.TimeoutExpired:
            # Ctrl-C's path: mutmut stops its workers and keeps the verdicts it has
            os.killpg(process.pid, signal.SIGINT)
            try:
                process.wait(timeout=60)
            except subprocess.TimeoutExpired:
                os.killpg(process.pid, signal.SIGKILL)
                process.wait()
            return False, process.returncode


def table(out: Path) -> str:
    """The report's table: per target, the full run's counts, then the same after the recheck
    against today's tests. Score: mutants detected (killed, or timed out: a mutant that makes a test
    hang is caught, if slowly) over mutants tested (a run stopped at its budget leaves some untested;
    a mutant no test reaches counts as tested and not detected)."""
    rows = ["| target | mutants (not tested) | killed | timed out | survived (no test reached) | score "
            "| after: killed | timed out | survived | score | run (wall) | recheck (wall) |",
            "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for name in TARGETS:
        if not (out / f"{name}.json").exists():
            continue
        run = json.loads((out / f"{name}.json").read_text())
        statuses = {m: s for per_file in run["statuses"].values() for m, s in per_file.items()}
        before = Counter(statuses.values())
        made, untested = sum(before.values()), before["not checked"]
        tested = made - untested
        missed = before["survived"] + before["no tests"]
        cells = [f"{made} ({untested})" if untested else made, before["killed"], before["timeout"],
                 f"{missed} ({before['no tests']})" if before["no tests"] else missed,
                 f"{100 * (before['killed'] + before['timeout']) / tested:.1f}%"]
        after_path = out / f"{name}.after.json"
        tail = ""
        if after_path.exists():
            recheck = json.loads(after_path.read_text())
            now = Counter({**statuses, **recheck["rechecked"]}.values())
            cells += [now["killed"], now["timeout"], now["survived"] + now["no tests"],
                      f"{100 * (now['killed'] + now['timeout']) / tested:.1f}%"]
            tail = f"{recheck['wall_s'] / 60:.0f} min" if "wall_s" in recheck else "by hand"
        else:
            cells += ["", "", "", ""]
        run_time = f"{run['wall_s'] / 60:.0f} min" + ("" if run["finished"] else ", stopped at its budget")
        rows.append("| " + " | ".join(str(c) for c in [name, *cells, run_time, tail]) + " |")
    return "\n".join(rows)


def cpu_name() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return f"{line.split(':', 1)[1].strip()}, {os.cpu_count()} CPUs"
    except OSError:
        pass
    return f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs"


def summary_line(report: dict) -> str:
    total = Counter()
    for counts in report["counts"].values():
        total.update(counts)
    made = sum(total.values())
    killed = total.get("killed", 0)
    score = f"{100 * killed / made:.1f}%" if made else "-"
    rest = ", ".join(f"{n} {s}" for s, n in sorted(total.items()) if s != "killed")
    return (f"{report['target']:13s} {made:4d} mutants, {killed:4d} killed ({score}){', ' + rest if rest else ''}; "
            f"{report['wall_s']:.0f} s wall{'' if report['finished'] else ' (stopped at the budget)'}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    # [] among the choices: argparse checks an empty positional list against them
    parser.add_argument("targets", nargs="*", choices=[[], *TARGETS], default=[], metavar="target",
                        help=f"{', '.join(TARGETS)}: which, in this order (default: all, fastest first)")
    parser.add_argument("--work", type=Path, default=Path(os.environ.get("TMPDIR", "/tmp")) / "d3rqn-mutation",
                        help="scratch folder for the copies (deleted and remade per target)")
    parser.add_argument("--out", type=Path, default=ROOT / "results" / "mutation",
                        help="where <target>.json goes")
    parser.add_argument("--budget", type=float, default=3600, help="wall seconds per target before it is stopped")
    parser.add_argument("--children", type=int, default=1, help="mutants tested at once (mutmut --max-children)")
    parser.add_argument("--timeout-multiplier", type=float, default=5.0,
                        help="per-mutant CPU limit: (tests' time + 1 s) x this x 2")
    parser.add_argument("--resume", action="store_true",
                        help="go on with a target stopped at its budget: same copy, only the mutants not yet tested")
    parser.add_argument("--recheck", action="store_true",
                        help="rerun only the last run's survivors and timeouts against today's tests")
    parser.add_argument("--table", action="store_true", help="print the report's table from the saved results")
    parser.add_argument("--all-update", action="store_true",
                        help="mutate every function of the learner's step (learner/update.py, loss.py, "
                             "update_path.py, trace_batch.py), not only its math")
    args = parser.parse_args()
    if not Path(mutmut_bin()).exists():
        sys.exit(f"no mutmut next to {sys.executable}: "
                 f"{Path(sys.executable).parent}/pip install mutmut=={MUTMUT_VERSION}")
    if args.table:
        print(table(args.out))
        return
    for name in args.targets or list(TARGETS):
        target = TARGETS[name]
        if name == "update" and args.all_update:
            target = Target(target.name, target.mutate, target.tests, (), target.deselect)
        if args.recheck:
            after = recheck_target(target, args.work, args.out, args.budget, args.children)
            print(f"{name}: the last run's survivors now {dict(Counter(after['rechecked'].values()))}")
            continue
        report = run_target(target, args.work, args.out, args.budget, args.children, args.timeout_multiplier,
                            args.resume)
        print(summary_line(report), flush=True)
        status = {m: s for statuses in report["statuses"].values() for m, s in statuses.items()}
        for mutant in report["survivors"]:
            print(f"  {status[mutant]:9s} {mutant}")


if __name__ == "__main__":
    main()
