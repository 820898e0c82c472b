"""The reference loop: the whole method in one process, one loop, top to bottom (as CleanRL's dqn_atari.py).

The distributed roles split this loop over processes: actors act
(actor/runner.py), the replay stores episodes and samples traces (replay/),
the learner updates and feeds the exploration strategy (learner/service.py).
Here it is one loop over env steps built from the same parts, with no copy of
them: the env of ``actor.sim.make_env`` stepped by the acting core of the actors
and the evaluation (actor/lockstep.py), the D3RQN of common/network.py, the
episode store of replay/store.py, the learner step of learner/update.py, the
strategies of common/exploration/ and the evaluation of actor/evaluation/.
Read it to follow the method, run it to check the stack against, and
benchmark the stack with it (deploy/bench/stack_speed.py).

Each env step:

1. act: uniformly at random until updates start, then the strategy's rule on
   the Q-values of the acting network: the online weights of the latest
   broadcast (every ``learner.weights_every`` updates), as an actor holds them,
   with the LSTM state zeroed at every episode start, on one torch thread as an
   actor runs (the updates get ``learner.torch_threads``);
2. store: a finished episode goes into the store whole (traces are sampled
   inside episodes: Bootstrapped Random Updates);
3. start: updates start the moment the store holds ``pace.start_episodes``
   episodes (decreasing epsilon: at ``pace.start_steps`` env steps), the
   replay's rate limiter's rule and start mark (common/pacing.py);
4. sample and update: one update per ``pace.env_steps_per_update`` env steps
   since the start mark, exactly;
5. feed the strategy what the learner feeds it: the env step count (decreasing
   epsilon), Q before and after each update (VDBE), and BMC's returns at the
   rate of ``exploration.bmc.observations``, with the learner's own function
   (learner/feed.py).

Training ends at an episode end once ``pace.total_env_steps`` steps are
taken; then the greedy policy is evaluated on the evaluation protocol.

    .venv/bin/python -m deploy.reference_loop --preset smoke --exploration.strategy vdbe
"""

from __future__ import annotations

import argparse
import copy
import math
import sys
import time
from collections import deque
from dataclasses import dataclass

import numpy as np
import torch

from actor.lockstep import Lockstep, episode_message, network_acts, training_actions
from actor.acting import actor_seed
from actor.sim import make_env
from common.config import Config
from common.config_cli import add_config_arguments, parse_config_or_exit, print_config
from common.exploration.build import make_strategy
from common.pacing import achieved_ratio, rate_limit_from_config, start_mark_of, updates_paid_for
from common.stored_state import state_row
from common.wire.state_rows import stored_units
from learner.feed import feed_strategy
from learner.service import Cadence
from learner.trace_batch import TraceArrays
from learner.update import DoubleQLearner
from replay.store import EpisodeStore


@dataclass
class LoopResult:
    env_steps: int
    episodes: int
    updates: int
    start_env_steps: int | None  # the start mark: env steps when updates started (by steps: start_steps)
    seconds_to_start: float  # wall time of the random phase
    seconds_updating: float  # wall time from the start of updates to the end of training
    mean_return: float  # of the last 100 episodes
    epsilon: float
    loss: float  # of the last update
    summaries: list | None = None  # the evaluation's rows (common.analysis.stats.SetSummary), if evaluated

    @property
    def env_steps_per_update(self) -> float:
        return achieved_ratio(self.env_steps, self.start_env_steps, self.updates)


def train(config: Config, evaluate_at_end: bool = True, update_seconds: float | None = None,
          log_period_s: float | None = None) -> LoopResult:
    """Trains to the step budget (or for `update_seconds` of wall time once updates start), then evaluates."""
    learner_config = config.learner
    seed = actor_seed(config.run.seed, 0)  # the seed actor 0 of the stack would use
    rng = np.random.default_rng(seed)
    env = make_env(config.env, seed=seed)
    core = Lockstep([env])  # the actors' acting core, with one simulator
    learner = DoubleQLearner(config.network, learner_config)
    acting = copy.deepcopy(learner.online).requires_grad_(False)
    strategy = make_strategy(config.exploration, config.network.n_actions)
    store = EpisodeStore(config.replay.capacity, int(config.replay.memory_budget_mb * 2**20),
                         learner_config.trace_length, config.replay.seed, stored_units(config))
    pace = rate_limit_from_config(config)
    log_every = log_period_s if log_period_s is not None else learner_config.log_period_s
    if learner_config.torch_threads:
        torch.set_num_threads(learner_config.torch_threads)
    update_threads = torch.get_num_threads()

    began = last_log = time.monotonic()
    started_at: float | None = None
    start_mark: float | None = None  # env steps when updates started (the rate limiter's start mark)
    acting_version = -1  # the broadcast the acting weights come from; -1: none yet, acts at random
    # The learner's broadcast rule, by updates only (no period): the loop's run must not depend on its speed.
    broadcasts = Cadence(learner_config.weights_every, 0.0)
    env_steps = episodes = 0
    returns: deque[float] = deque(maxlen=100)
    result = None
    while True:
        if not core.running:  # a new episode: reset the env and the LSTM state
            core.begin(0, options={"start_set": "train"})
            state = acting.initial_state(1)
        episode = core.running[0]

        # 1. act (learner.stored_state: first record the state the network takes this frame in)
        if learner_config.stored_state:
            episode.states.append(state_row(*state))
        if strategy.started or learner_config.stored_state:  # the random phase too: real stored states
            torch.set_num_threads(1)  # one frame: more threads only wait for each other
            with torch.inference_mode():
                frame = torch.from_numpy(episode.observation).view(1, 1, *episode.observation.shape)
                q_values, state = acting(frame.to(learner.device), state)
            torch.set_num_threads(update_threads)
        acted_on = q_values[0].cpu().numpy() if network_acts(strategy, acting_version) else None
        (action,) = training_actions(strategy, acted_on, [rng], config.network.n_actions)
        episode_over = bool(core.step({0: action}, tag=acting_version))
        env_steps += 1

        # 2. store: a finished episode goes in whole, as an actor sends it
        if episode_over:
            store.add(episode_message(episode, actor_id=0, seed=seed, episode_index=episodes,
                                      epsilon=float(strategy.epsilon)))
            episodes += 1
            returns.append(sum(episode.rewards))

        # 3. start: the episode just stored may start the updates, by the replay's rate limiter's rule
        # (common/pacing.py: by episodes, the steps so far are the start mark; by steps, start_steps)
        if start_mark is None and episode_over:
            start_mark = start_mark_of(pace, env_steps - episode.length, env_steps, len(store))
            if start_mark is not None:
                started_at = time.monotonic()
                strategy.start()
                acting.load_state_dict(learner.online.state_dict())  # the learner's first broadcast, version 0
                acting_version = 0

        # 4. sample and update, one update per env_steps_per_update steps since the start
        while start_mark is not None and learner.updates < updates_paid_for(env_steps, start_mark,
                                                                            pace.env_steps_per_update):
            batch = store.sample(learner_config.batch_size)
            result = learner.update(TraceArrays.from_batch(batch), with_q_after=strategy.needs_q_after)
            # 5. feed the strategy, as learner/service.py does after each update (the learner knows
            # the steps of the episodes the replay has received; here every step taken is known)
            feed_strategy(strategy, result, env_steps, config)
            if broadcasts.due(learner.updates):  # broadcast: the acting weights catch up
                acting.load_state_dict(learner.online.state_dict())
                acting_version = learner.updates

        now = time.monotonic()
        if now - last_log >= log_every:
            last_log = now
            print(f"reference loop: env steps {env_steps:,d}, episodes {episodes:,d}, updates {learner.updates:,d}, "
                  f"epsilon {strategy.epsilon:.3f}, mean return (last 100) {np.mean(returns) if returns else 0:.2f}",
                  file=sys.stderr, flush=True)
        out_of_time = update_seconds is not None and started_at is not None and now - started_at >= update_seconds
        if out_of_time or (episode_over and env_steps >= config.pace.total_env_steps):
            break

    env.close()
    finished = time.monotonic()
    outcome = LoopResult(
        env_steps=env_steps, episodes=episodes, updates=learner.updates,
        start_env_steps=None if start_mark is None else int(start_mark),
        seconds_to_start=(started_at or finished) - began,
        seconds_updating=finished - started_at if started_at is not None else 0.0,
        mean_return=float(np.mean(returns)) if returns else math.nan, epsilon=float(strategy.epsilon),
        loss=result.loss if result is not None else math.nan)
    if evaluate_at_end:
        from actor.evaluation.protocol import evaluate  # spawns the evaluation's worker processes
        outcome.summaries = evaluate(config, learner.online_weights(), policies=("greedy",), show_status=False)[1]
    return outcome


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="reference-loop", description=__doc__.splitlines()[0])
    parser.add_argument("--no-evaluate", action="store_true", help="skip the evaluation at the end")
    add_config_arguments(parser)
    args, config = parse_config_or_exit(parser, argv)
    print_config("reference-loop", config)
    result = train(config, evaluate_at_end=not args.no_evaluate)
    print(f"reference loop: {result.env_steps:,d} env steps, {result.episodes:,d} episodes, {result.updates:,d} "
          f"updates ({result.env_steps_per_update:.3f} env steps per update since updates started at "
          f"{result.start_env_steps} env steps); random phase {result.seconds_to_start:.1f} s, updating "
          f"{result.seconds_updating:.1f} s; mean return of the last 100 episodes {result.mean_return:.2f}")
    if result.summaries:
        from common.analysis.tables import markdown_table
        print(markdown_table(result.summaries, config.evaluation.reward_bins, config.evaluation.confidence))


if __name__ == "__main__":
    main()
