"""The actor's acting: its simulators on the acting core (actor/lockstep.py), its batched network and its
exploration strategy, the learner's mail applied between steps, and the episodes they make. The process
around it, its session, threads and loop, is actor/runner.py.
"""

from __future__ import annotations

import logging
import secrets
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np
import torch

from actor.batched_q import BatchedQ, choose_precision
from actor.lockstep import Lockstep, Trajectory, episode_message, network_acts, training_actions
from actor.mailbox import Mailbox
from actor.sim import make_env
from common.config import Config
from common.exploration.base import ExplorationStrategy
from common.network import initial_network
from common.pacing import env_steps_ceiling
from common.rejections import Rejections
from common.wire.exploration_state import ExplorationState, follow
from common.wire.messages import Episode, EpisodeRecord

log = logging.getLogger("actor")


def actor_seed(run_seed: int, actor_id: int) -> int:
    """Independent, reproducible streams per actor, derived from the run seed."""
    return int(np.random.SeedSequence([run_seed, actor_id]).generate_state(1)[0])


def env_seed(actor_seed: int, env_index: int) -> int:
    """The seed of an actor's env_index-th simulator and its exploration draws: env 0 keeps the actor's own,
    so that one env per actor is the single-env actor; the others derive theirs from it and their index."""
    if env_index == 0:
        return actor_seed
    return int(np.random.SeedSequence([actor_seed, env_index]).generate_state(1)[0])


@dataclass
class EnvSlot:
    """One of an actor's simulators: its seed, its own exploration draws, and its episode's off-greedy actions
    (None once one was taken without Q-values)."""

    index: int
    env: Any
    seed: int
    rng: np.random.Generator
    off_greedy: int | None = 0


class Actor:
    """actor.envs_per_actor simulators, one network, one exploration strategy."""

    def __init__(self, config: Config, actor_id: int) -> None:
        self.config = config
        self.actor_id = actor_id
        self.seed = actor_seed(config.run.seed, actor_id)
        seeds = [env_seed(self.seed, index) for index in range(config.actor.envs_per_actor)]
        self.slots = [EnvSlot(index, make_env(config.env, seed=seed), seed, np.random.default_rng(seed))
                      for index, seed in enumerate(seeds)]
        self.lockstep = Lockstep([slot.env for slot in self.slots])
        # the learner's initial network (learner.seed): what the random phase runs for its stored states
        self.network = initial_network(config.network, config.learner.seed).eval()
        self.batched_q = BatchedQ(self.network, len(self.slots),
                                  choose_precision(self.network, len(self.slots), config.actor.inference))
        # The learner's strategy, rebuilt from its first exploration state; until then none, and the actor acts
        # uniformly at random (actor/lockstep.py network_acts), as every strategy does before updates start.
        self.strategy: ExplorationStrategy | None = None
        self.weights_version = -1  # no weights yet: act uniformly at random
        self.weights_behind_max = 0  # the most updates behind the learner its weights were when the stats looked
        self.episode_index = 0  # episodes ended so far, the number of the next to end
        self.episodes_started = 0
        self.weights_downloads = 0  # actor.weights_download: downloads completed
        self.weights_download_s = 0.0  # how long the last one took
        self.weights_downloaded_at = time.monotonic()  # when the last one finished (or the actor started)
        self._ended: deque[tuple[Episode, EpisodeRecord]] = deque()  # run_episode's, not yet returned
        self.incarnation = secrets.randbits(62) | 1  # names this process's episodes (never 0: unnamed)
        self.rejections = Rejections(log)
        shapes = {name: tuple(tensor.shape) for name, tensor in self.network.state_dict().items()}
        self.mailbox = Mailbox(shapes, self.rejections, env_steps_ceiling(config), config.actor.silence_hold_s)

    def apply_mail(self) -> None:
        weights, exploration = self.mailbox.take()
        if weights is not None:
            try:
                self.batched_q.load_weights(weights.tensors)
                self.weights_version = weights.version
            except ValueError as error:
                self.rejections.reject("weights_values", f"weights version {weights.version}: {error}")
        if exploration is not None:
            self.follow(exploration)

    def follow(self, message: ExplorationState) -> None:
        """Takes the learner's exploration state: the same strategy with the same params is loaded, another is
        rebuilt from the state alone, with one log line. A state that cannot be used is counted, logged and
        skipped: the actor acts on as before."""
        try:
            strategy = follow(self.strategy, message, self.config.network.n_actions)
        except ValueError as error:
            self.rejections.reject("exploration_invalid", f"the learner's exploration state: {error}")
            return
        if strategy is not self.strategy:
            log.info("following the learner's exploration: %s %s%s", strategy.name, strategy.params(),
                     self._before(strategy.name))
            self.strategy = strategy

    def _before(self, name: str) -> str:
        """What the actor acted on before: a user who gave it another strategy learns that the learner's wins."""
        if self.strategy is not None:
            return f" (until now {self.strategy.name} {self.strategy.params()})"
        configured = self.config.exploration.strategy
        return "" if configured == name else f" (this actor's config names {configured}; the learner's state decides)"


    def uses_network(self) -> bool:
        return network_acts(self.strategy, self.weights_version)

    @property
    def running(self) -> list[EnvSlot]:
        return [slot for slot in self.slots if slot.index in self.lockstep.running]

    def step(self, may_start: Callable[[], bool] = lambda: True) -> list[tuple[Episode, EpisodeRecord]]:
        """One lockstep step: each idle simulator begins an episode if may_start() says so, then every
        running one takes one action. Returns the episodes that ended, in simulator order."""
        self.apply_mail()
        for slot in self.slots:
            if slot.index not in self.lockstep.running and may_start():
                self._begin(slot)
        running = self.running
        if running and self.config.learner.stored_state:  # the state each network takes this step's frame in
            for slot, row in zip(running, self.batched_q.state_rows([slot.index for slot in running])):
                self.lockstep.running[slot.index].states.append(row)
        actions = dict(zip([slot.index for slot in running], self._actions(running)))
        return [self._finish(self.slots[index], trajectory)
                for index, trajectory in self.lockstep.step(actions, tag=self.weights_version)]

    def run_episode(self, stop: threading.Event) -> tuple[Episode, EpisodeRecord] | None:
        """The next episode to end, every idle simulator starting its next at once (no rate limiter):
        with one simulator, one whole episode. None if stopped first."""
        while not self._ended:
            if stop.is_set():
                return None
            self._ended.extend(self.step())
        return self._ended.popleft()

    def _begin(self, slot: EnvSlot) -> None:
        self.lockstep.begin(slot.index, options={"start_set": "train"})
        self.batched_q.reset(slot.index)
        slot.off_greedy = 0
        self.episodes_started += 1

    def _actions(self, running: list[EnvSlot]) -> list[int]:
        """One action per running simulator, each drawn from its own generator (and its Q-values' row)."""
        if not running:
            return []
        rngs = [slot.rng for slot in running]
        if not self.uses_network():
            if self.config.learner.stored_state:
                # The random phase acts uniformly but still runs the network, so that its episodes store the
                # initial network's real LSTM states, not zero rows mid-episode (docs/method.md, learner.stored_state).
                self._q_values(running)
            for slot in running:
                slot.off_greedy = None
            return training_actions(self.strategy, None, rngs, self.config.network.n_actions)
        q_values = self._q_values(running).numpy()
        actions = training_actions(self.strategy, q_values, rngs, self.config.network.n_actions)
        for slot, row, action in zip(running, q_values, actions):
            if slot.off_greedy is not None:
                slot.off_greedy += int(action != int(np.argmax(row)))
        return actions

    def _q_values(self, running: list[EnvSlot]) -> torch.Tensor:
        """The running simulators' Q-values on their latest frames; advances their LSTM states."""
        return self.batched_q.q_values([slot.index for slot in running], [self.lockstep.running[slot.index].observation for slot in running])

    def _finish(self, slot: EnvSlot, trajectory: Trajectory) -> tuple[Episode, EpisodeRecord]:
        epsilon = float(self.strategy.epsilon) if self.uses_network() else 1.0
        episode = episode_message(trajectory, actor_id=self.actor_id, seed=slot.seed,
                                  episode_index=self.episode_index, epsilon=epsilon, incarnation=self.incarnation,
                                  in_hand=self.config.actor.envs_per_actor + self.config.actor.queue_episodes)
        record = EpisodeRecord(
            actor_id=self.actor_id, episode_index=self.episode_index, length=trajectory.length,
            episode_return=float(sum(trajectory.rewards)), collided=trajectory.collided,
            start_set=episode.start_set, start_index=episode.start_index, epsilon=epsilon,
            weights_version=self.weights_version, wall_time=time.monotonic() - trajectory.started, time=time.time(),
            off_greedy=-1 if slot.off_greedy is None else slot.off_greedy)
        self.episode_index += 1
        return episode, record
