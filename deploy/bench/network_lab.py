"""Figures from the multi-host lab (deploy/labs/netns_lab.py) on this machine; needs root, iproute2, nftables.

- hosts: env steps/s and learner updates/s with 1, 2 and 4 actor hosts (one actor each), over
  `--seconds` of training after the learner's first updates;
- cap: actor 1's link capped at `--mbit` (20 Mbit/s) while the learner broadcasts the paper's network
  (48.6 MB as float32, 24.3 MB as float16), against the same span before the cap: the learner's
  updates/s, actor 1's episodes, and how far its weights lagged (its own warnings); with `--download`,
  actor 1 downloads the weights piece by piece (actor.weights_download) instead of receiving broadcasts.

The figures come from the processes' own lines: the learner's status line (updates, env steps) read
every second, and the actor's "acting on weights vN, M updates behind" warnings and stopped line. The
smoke preset, with the run's budget out of reach; the actors on other hosts share this machine's cores
with the hub, so on a small machine the figures say what the cores allow, not the network.

    .venv/bin/python deploy/bench/network_lab.py hosts [--hosts 1,2,4] [--seconds 60]
    .venv/bin/python deploy/bench/network_lab.py cap [--mbit 20] [--encodings float32,float16] [--seconds 90] [--download]
"""

from __future__ import annotations

import argparse
import re
import tempfile
import time
from pathlib import Path

from common.eta import clock_time
from deploy.labs.netns_lab import Lab, config_flags, why_no_lab

BASE = ["--preset", "smoke", "--pace.total_env_steps", "100000000", "--run.runs_dir", "runs"]
STATUS = re.compile(r"updates (\d+), env steps (\d+),")
BEHIND = re.compile(r"acting on weights v\d+, (\d+) updates behind")
WARM_UP_S = 240.0


def learner_counts(log: Path) -> tuple[int, int] | None:
    """(updates, env steps) of the learner's last status line, None before the first."""
    found = STATUS.findall(log.read_text(errors="replace")) if log.exists() else []
    return (int(found[-1][0]), int(found[-1][1])) if found else None


def start_lab(directory: Path, actor_hosts: int, flags: list[str], first_actor: list[str] = ()) -> Lab:
    lab = Lab(directory, actor_hosts)
    lab.build()
    lab.start("hub", "replay", ["-m", "replay.main", *config_flags(False, "replay"), *BASE, *flags])
    lab.start("hub", "learner", ["-m", "learner.main", *config_flags(False, "learner"), *BASE, *flags])
    for n in range(1, actor_hosts + 1):
        lab.start(f"a{n}", "actor", ["-m", "actor.main", *config_flags(False, "actor"), "--actor.actor_id", str(n),
                                     *BASE, *flags, *(first_actor if n == 1 else ())])
    return lab


def wait_for_updates(lab: Lab, log: Path) -> None:
    deadline = time.monotonic() + WARM_UP_S
    while (learner_counts(log) or (0, 0))[0] < 3:
        lab.alive()
        if time.monotonic() > deadline:
            raise RuntimeError(f"no updates within {WARM_UP_S:.0f} s\n{lab.tails()}")
        time.sleep(1.0)


def speeds_over(lab: Lab, log: Path, seconds: float, label: str) -> tuple[float, float]:
    """(updates/s, env steps/s) over the next `seconds`, with progress and an ETA."""
    first, started = learner_counts(log), time.monotonic()
    while (elapsed := time.monotonic() - started) < seconds:
        lab.alive()
        time.sleep(min(5.0, seconds - elapsed))
        elapsed = time.monotonic() - started
        print(f"  {label}: {elapsed:.0f}/{seconds:.0f} s, ETA {clock_time(max(0.0, seconds - elapsed))}", flush=True)
    last = learner_counts(log)
    took = time.monotonic() - started
    return (last[0] - first[0]) / took, (last[1] - first[1]) / took


def lags(actor_log: Path) -> tuple[int, int]:
    """(most updates behind, warnings) from an actor's "acting on weights vN, M updates behind" lines."""
    behind = [int(n) for n in BEHIND.findall(actor_log.read_text(errors="replace"))] if actor_log.exists() else []
    return max(behind, default=0), len(behind)


def hosts(args) -> None:
    rows = []
    for count in args.hosts:
        with tempfile.TemporaryDirectory() as directory:
            lab = start_lab(Path(directory), count, ["--network.lstm_units", "16"])
            try:
                log = Path(directory) / "hub-learner.log"
                wait_for_updates(lab, log)
                rows.append((count, *speeds_over(lab, log, args.seconds, f"{count} actor host(s)")))
            finally:
                lab.teardown()
    print("\n| actor hosts | learner updates/s | env steps/s |\n|---:|---:|---:|")
    for count, updates, steps in rows:
        print(f"| {count} | {updates:.2f} | {steps:.1f} |")


def cap(args) -> None:
    rows = []
    for encoding in args.encodings:
        with tempfile.TemporaryDirectory() as directory:
            download = ["--actor.weights_download", "true"] if args.download else []
            lab = start_lab(Path(directory), 2, ["--learner.weights_encoding", encoding], download)
            try:
                log = Path(directory) / "hub-learner.log"
                wait_for_updates(lab, log)
                free = speeds_over(lab, log, args.seconds, f"{encoding}, uncapped")
                lab.cap("a1", args.mbit)
                capped = speeds_over(lab, log, args.seconds, f"{encoding}, actor 1 at {args.mbit} Mbit/s")
                lab.heal("a1")
                behind = [lags(Path(directory) / f"a{n}-actor.log") for n in (1, 2)]
                rows.append((encoding, free[0], capped[0], capped[1], *behind[0], behind[1][0]))
            finally:
                lab.teardown()
    print(f"\n| weights | learner updates/s uncapped | with actor 1 at {args.mbit} Mbit/s | env steps/s capped | "
          "actor 1's weights, most updates behind | its warnings | actor 2's (uncapped), most behind |"
          "\n|---|---:|---:|---:|---:|---:|---:|")
    for encoding, free_speed, capped_speed, steps, most, warnings, other in rows:
        print(f"| {encoding} | {free_speed:.2f} | {capped_speed:.2f} | {steps:.1f} | {most} | {warnings} | {other} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    commands = parser.add_subparsers(dest="command", required=True)
    hosts_parser = commands.add_parser("hosts", help="throughput with 1, 2 and 4 actor hosts")
    hosts_parser.add_argument("--hosts", type=lambda text: [int(n) for n in text.split(",")], default=[1, 2, 4])
    hosts_parser.add_argument("--seconds", type=float, default=60.0, help="the span measured, after warm-up")
    cap_parser = commands.add_parser("cap", help="one actor's link capped while the paper's weights are broadcast")
    cap_parser.add_argument("--mbit", type=float, default=20.0, help="the cap on actor 1's link, both ways")
    cap_parser.add_argument("--encodings", type=lambda text: text.split(","), default=["float32", "float16"])
    cap_parser.add_argument("--seconds", type=float, default=90.0, help="each span: uncapped, then capped")
    cap_parser.add_argument("--download", action="store_true",
                            help="actor 1 downloads the weights in pieces (actor.weights_download) instead")
    args = parser.parse_args()
    reason = why_no_lab(faults=True)
    if reason:
        raise SystemExit(f"cannot run the lab here: {reason}")
    {"hosts": hosts, "cap": cap}[args.command](args)


if __name__ == "__main__":
    main()
