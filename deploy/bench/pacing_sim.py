"""The rate limiter's pace on a simulated clock: how long a fast learner waits for data, and how far the
ratio strays, against the error buffer and the actors' hold.

The real code decides: the replay's RateLimiter (replay/rate_limiter.py) counts the steps and the
batches, its hold goes to each actor's Mailbox as the replay's rate message (the RateState
of ``limiter.state()``, announced when the hold changes, as the replay's reply thread does), and an idle
simulator begins its next episode when the actor's EpisodeGate (actor/gate.py) lets it. The learner
stops when its RunClock (learner/service.py) says the run is closed and paid for. Only time is simulated:

- `actors` actors of one simulator each, at a steady speed drawn per actor from 200-1,000 env steps/s
  (scaled, where `free_over_need` is given, so that together they step that many times the
  `updates_per_s` x `env_steps_per_update` the ratio needs); an episode arrives whole when it ends;
- episode lengths from 30 to 2,000 steps (env.max_steps): "mixed", log-uniform, or "long", half of
  them cut at 2,000 (a policy that drives) and the rest log-uniform;
- updates start at `start_steps` env steps (the drive preset's 28,000); the budget pays for
  `budget_updates` updates;
- a learner that takes a batch whenever the limiter serves one and spends 1/updates_per_s on it; it
  is *idle* while it asks and the limiter holds its batch (the learner ahead by the error buffer).

Messages take no time here: the word reaches the actors at once. What the simulation leaves out is the
learner's own wait on the batch pipeline (sampling, transport, decoding), which a real run's "waiting
for data" includes (docs/architecture.md, "The pace of a fast learner").

    .venv/bin/python deploy/bench/pacing_sim.py [--seeds 3] [--buffers 50,700] [--holds 50,700,2000]
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import math
import statistics
import time

import numpy as np

from actor.gate import EpisodeGate, HoldLog
from actor.mailbox import Mailbox
from common.pacing import RateLimit
from learner.service import RunClock
from replay.rate_limiter import RateLimiter

MAX_STEPS = 2_000  # env.max_steps
MIN_STEPS = 30
SPEEDS = (200.0, 1_000.0)  # one actor's free env steps/s
NEVER = math.inf


@dataclasses.dataclass(frozen=True)
class Scenario:
    updates_per_s: float
    error_buffer: float  # pace.error_buffer_updates: the learner's lead
    hold_buffer: float | None = None  # the actors' lead (None: the error buffer, as before issue 40)
    free_over_need: float | None = None  # None: the actors' speeds as drawn
    episodes: str = "mixed"
    seed: int = 0
    actors: int = 12
    env_steps_per_update: float = 4.0
    start_steps: int = 28_000
    budget_updates: int = 30_000

    def limit(self) -> RateLimit:
        extra = {} if self.hold_buffer is None else {"hold_buffer": self.hold_buffer}
        return RateLimit(self.env_steps_per_update, start_episodes=1, start_steps=self.start_steps,
                         error_buffer=self.error_buffer, start_by_steps=True,
                         total_env_steps=self.start_steps + int(self.budget_updates * self.env_steps_per_update),
                         **extra)


@dataclasses.dataclass
class Outcome:
    """What one simulated run saw, from the first update to the learner's stop."""

    scenario: Scenario
    free_speed: float  # the actors' env steps/s together, unheld
    learning_s: float = 0.0
    idle_s: float = 0.0
    updates: int = 0
    mid_ratio: float = math.nan  # env steps per update when half the budget's updates were made
    end_ratio: float = math.nan
    end_shortfall: float = math.nan  # updates the stored steps paid for and the learner did not make
    refused: int = 0  # episodes that arrived after the run closed

    @property
    def idle_share(self) -> float:
        return self.idle_s / self.learning_s if self.learning_s else math.nan

    def deviation(self, ratio: float) -> float:
        return ratio / self.scenario.env_steps_per_update - 1.0


def episode_lengths(kind: str, rng: np.random.Generator):
    """An endless draw of episode lengths of one actor."""
    while True:
        if kind == "long" and rng.random() < 0.5:
            yield MAX_STEPS
        else:
            yield int(round(math.exp(rng.uniform(math.log(MIN_STEPS), math.log(MAX_STEPS)))))


def actor_speeds(scenario: Scenario) -> list[float]:
    rng = np.random.default_rng([scenario.seed, 1_000])
    speeds = rng.uniform(*SPEEDS, size=scenario.actors)
    if scenario.free_over_need is not None:
        need = scenario.updates_per_s * scenario.env_steps_per_update
        speeds *= scenario.free_over_need * need / speeds.sum()
    return [float(speed) for speed in speeds]


class Replay:
    """The limiter and its announcements: a changed hold (or close) goes out as the rate message."""

    def __init__(self, limiter: RateLimiter, mailboxes: list[Mailbox]) -> None:
        self.limiter = limiter
        self.mailboxes = mailboxes
        self.stored = 0
        self._announced: tuple | None = None

    def announce(self, now: float) -> None:
        said = (self.limiter.hold_reason(), self.limiter.closed)
        if said != self._announced:
            self._announced = said
            message = self.limiter.state(now)
            for mailbox in self.mailboxes:
                mailbox.offer_rate(message)

    def take(self, steps: int) -> bool:
        """An episode arrives; False if the run is closed (refused, as the replay does)."""
        if self.limiter.closed:
            return False
        self.stored += 1
        self.limiter.on_episode(steps, self.stored)
        return True


class Learner:
    """One batch at a time: busy 1/updates_per_s after each, idle while the limiter holds its ask."""

    def __init__(self, scenario: Scenario, limiter: RateLimiter) -> None:
        self.limiter = limiter
        self.seconds_per_update = 1.0 / scenario.updates_per_s
        self.clock = RunClock()
        self.free_at = NEVER  # the end of the update in progress; NEVER while it waits
        self.waiting_since: float | None = 0.0
        self.first_update_at: float | None = None
        self.updates = 0
        self.idle_s = 0.0
        self.stopped = False

    def ask(self, now: float) -> None:
        """At `now` the learner wants a batch: it takes one if served, or waits (idle once started)."""
        limiter = self.limiter
        self.clock.observe_rate(limiter.state(now))
        if self.clock.finished(self.updates):
            self.stopped, self.free_at = True, NEVER
            self._end_wait(now)
            return
        if not limiter.may_serve():
            self.free_at = NEVER
            if self.waiting_since is None:
                self.waiting_since = now
            return
        self._end_wait(now)
        if self.first_update_at is None:
            self.first_update_at = now
        limiter.on_served()
        self.updates += 1
        self.free_at = now + self.seconds_per_update

    def _end_wait(self, now: float) -> None:
        if self.waiting_since is not None and self.first_update_at is not None:
            self.idle_s += now - self.waiting_since
        self.waiting_since = None


def simulate(scenario: Scenario) -> Outcome:
    """One run, from the first episode to the learner's stop."""
    limiter = RateLimiter(scenario.limit())
    speeds = actor_speeds(scenario)
    outcome = Outcome(scenario, free_speed=sum(speeds))
    now = 0.0
    mailboxes = [Mailbox() for _ in speeds]
    gates = [EpisodeGate(mailbox, HoldLog(math.inf, clock=lambda: now), more=lambda: True)
             for mailbox in mailboxes]
    lengths = [episode_lengths(scenario.episodes, np.random.default_rng([scenario.seed, actor]))
               for actor in range(len(speeds))]
    replay, learner = Replay(limiter, mailboxes), Learner(scenario, limiter)
    ends, steps = [NEVER] * len(speeds), [0] * len(speeds)
    replay.announce(now)
    while not learner.stopped:
        for actor, end in enumerate(ends):  # an idle simulator begins its next episode if the gate lets it
            if end == NEVER and gates[actor]():
                steps[actor] = next(lengths[actor])
                ends[actor] = now + steps[actor] / speeds[actor]
        actor = min(range(len(ends)), key=ends.__getitem__)
        now = min(ends[actor], learner.free_at)
        if now == NEVER:
            raise RuntimeError(f"deadlock: every actor held and the learner waiting ({limiter.state(now)})")
        if ends[actor] <= learner.free_at:
            ends[actor] = NEVER
            outcome.refused += not replay.take(steps[actor])
            if learner.free_at == NEVER:
                learner.ask(now)
        else:
            learner.ask(now)
            if learner.updates == scenario.budget_updates // 2 and math.isnan(outcome.mid_ratio):
                outcome.mid_ratio = limiter.env_steps_per_update()
        replay.announce(now)
    outcome.learning_s = now - learner.first_update_at
    outcome.idle_s, outcome.updates = learner.idle_s, learner.updates
    outcome.end_ratio = (limiter.env_steps - limiter.start_mark) / learner.updates
    outcome.end_shortfall = limiter.updates_due - learner.updates
    return outcome


# --- the table --------------------------------------------------------------------------------------------


def scenarios(args) -> list[Scenario]:
    """Every combination the command line names."""
    found = []
    for updates_per_s in args.updates_per_s:
        for free in args.free_over_need:
            for episodes in args.episodes:
                for buffer, hold in args.pacings:
                    for seed in range(args.seeds):
                        found.append(Scenario(updates_per_s, buffer, hold, free, episodes, seed,
                                              budget_updates=args.budget_updates))
    return found


def row(group: list[Outcome]) -> str:
    """One table row: a scenario over its seeds (the worst seed in brackets)."""
    first = group[0].scenario
    idle = [outcome.idle_share for outcome in group]
    mid = [outcome.deviation(outcome.mid_ratio) for outcome in group]
    end = [outcome.deviation(outcome.end_ratio) for outcome in group]
    shortfall = [outcome.end_shortfall for outcome in group]
    past = statistics.mean(outcome.updates / first.budget_updates - 1.0 for outcome in group)
    hold = first.error_buffer if first.hold_buffer is None else first.hold_buffer
    free = statistics.mean(outcome.free_speed for outcome in group) / (first.updates_per_s * first.env_steps_per_update)
    return (f"| {first.updates_per_s:g} | {free:.1f} | {first.episodes} | {first.error_buffer:g} | {hold:g} "
            f"| {100 * statistics.mean(idle):.1f} [{100 * max(idle):.1f}] "
            f"| {100 * statistics.mean(mid):+.2f} [{100 * max(mid, key=abs):+.2f}] "
            f"| {100 * statistics.mean(end):+.3f} [{100 * max(end, key=abs):+.3f}] "
            f"| {min(shortfall):.2f} to {max(shortfall):.2f} | {100 * past:.1f} |")


HEADER = ("| updates/s | free / need | episodes | learner's lead B | actors' lead H | learner idle % (worst) "
          "| ratio off mid-run % (worst) | ratio off at the end % (worst) | updates unpaid at the close "
          "| updates past the budget % |\n"
          "|---:|---:|---|---:|---:|---:|---:|---:|---|---:|")


def pacing(text: str) -> tuple[float, float | None]:
    """"B" (the actors' lead the same) or "B/H"."""
    buffer, _, hold = text.partition("/")
    return float(buffer), float(hold) if hold else None


def numbers(text: str, kind=float) -> list:
    return [None if part == "drawn" else kind(part) for part in text.split(",")]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--updates-per-s", type=numbers, default=[60.0, 300.0])
    parser.add_argument("--free-over-need", type=numbers, default=[1.2, 2.0, None],
                        help="the actors' free speed over the ratio's need; 'drawn': as drawn (200-1,000 each)")
    parser.add_argument("--episodes", type=lambda text: text.split(","), default=["mixed", "long"])
    parser.add_argument("--pacings", type=lambda text: [pacing(part) for part in text.split(",")],
                        default=[(50.0, None), (700.0, None)],
                        help="B or B/H: the learner's lead and the actors' (H: pace.hold_updates)")
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--budget-updates", type=int, default=30_000)
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING)
    started = time.perf_counter()
    print(HEADER)
    group: list[Outcome] = []
    for scenario in scenarios(args):
        group.append(simulate(scenario))
        if scenario.seed == args.seeds - 1:
            print(row(group), flush=True)
            group = []
    print(f"\n{args.seeds} seeds a row, mean and [worst]; {time.perf_counter() - started:.0f} s")


if __name__ == "__main__":
    main()
