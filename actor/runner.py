"""The actor loop: drive the simulator with the newest policy and publish whole episodes.

The network is stepped one frame at a time; its LSTM state lives for one
episode. Weights and exploration state arrive on Zenoh callbacks, which only
park the newest message in a mailbox; the stepping loop picks it up between
steps, so a slow or absent learner never blocks driving.

The learner is the authority on exploration: a state naming another strategy
or other params than this actor's config replaces the actor's strategy (one log
line). Between episodes the actor obeys the replay's rate limiter: it holds its
next episode while the replay says the learner is behind (``replay/rate``).
"""

from __future__ import annotations

import dataclasses
import logging
import signal
import threading
import time
from dataclasses import dataclass, field

import numpy as np
import torch

from actor.sim import make_env
from common.config import Config
from common.exploration import make_strategy, same_strategy, strategy_from_state
from common.logs import Every, setup_logging
from common.network import D3RQN, load_numpy_weights
from common.transport import Keys, RateLimitedLog, declare_liveliness, open_session, publisher, request, subscribe
from common.wire import Episode, EpisodeRecord, ExplorationState, FrameStack, Stats, Weights

log = logging.getLogger("actor")

LATEST_WEIGHTS_TIMEOUT_S = 30.0
REPLAY_WAIT_LOG_S = 10.0


def actor_seed(run_seed: int, actor_id: int) -> int:
    """Independent, reproducible streams per actor, derived from the run seed."""
    return int(np.random.SeedSequence([run_seed, actor_id]).generate_state(1)[0])


class Mailbox:
    """Holds only the newest message of each kind; written by callbacks, read by the loop."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._weights: Weights | None = None
        self._exploration: ExplorationState | None = None
        self.hold_reason = ""  # the replay's word on the next episode: "behind", "budget" or "" (go)

    def offer_weights(self, message: Weights, key: str = "") -> None:
        with self._lock:
            if self._weights is None or message.version > self._weights.version:
                self._weights = message

    def offer_exploration(self, message: ExplorationState, key: str = "") -> None:
        with self._lock:
            self._exploration = message

    def offer_rate(self, message: Stats, key: str = "") -> None:
        """The replay's rate limiter; kept, not taken: the hold is read repeatedly."""
        reason = message.values.get("hold_reason", "")
        with self._lock:
            self.hold_reason = reason if isinstance(reason, str) else ""

    def must_hold(self) -> str:
        """Why the next episode must wait ("" when it may start); no word from a replay: go."""
        with self._lock:
            return self.hold_reason

    def take(self) -> tuple[Weights | None, ExplorationState | None]:
        with self._lock:
            taken = (self._weights, self._exploration)
            self._weights = self._exploration = None
            return taken


@dataclass
class EpisodeBuffer:
    frames: list[np.ndarray] = field(default_factory=list)
    actions: list[int] = field(default_factory=list)
    rewards: list[float] = field(default_factory=list)
    versions: list[int] = field(default_factory=list)


class Actor:
    """One simulator, one network, one exploration strategy."""

    def __init__(self, config: Config, actor_id: int) -> None:
        self.config = config
        self.actor_id = actor_id
        self.seed = actor_seed(config.run.seed, actor_id)
        self.rng = np.random.default_rng(self.seed)
        self.env = make_env(config.env, seed=self.seed)
        self.network = D3RQN(config.network).eval()
        self.strategy = make_strategy(config.exploration, config.network.n_actions)
        self.weights_version = -1  # no weights yet: act uniformly at random
        self.episode_index = 0
        self.mailbox = Mailbox()
        self._warn = RateLimitedLog()

    def apply_mail(self) -> None:
        weights, exploration = self.mailbox.take()
        if weights is not None and weights.version > self.weights_version:
            try:
                load_numpy_weights(self.network, weights.tensors)
                self.weights_version = weights.version
            except ValueError as error:
                log.warning("ignoring weights version %d: %s", weights.version, error)
        if exploration is not None:
            self.follow(dataclasses.asdict(exploration))

    def follow(self, state: dict) -> None:
        """Loads the learner's exploration state; another strategy or other params replace this
        actor's strategy, with one log line. A state that cannot be used is logged and skipped."""
        try:
            if same_strategy(self.strategy, state):
                self.strategy.load_state_dict(state)
                return
            replacement = strategy_from_state(state, self.config.network.n_actions)
        except ValueError as error:
            self._warn.warning("ignoring the learner's exploration state: %s", error)
            return
        log.info("following the learner's exploration: %s %s (this actor was configured with %s %s)",
                 replacement.name, replacement.params(), self.strategy.name, self.strategy.params())
        self.strategy = replacement

    def uses_network(self) -> bool:
        return self.weights_version >= 0 and self.strategy.started

    def run_episode(self, stop: threading.Event) -> tuple[Episode, EpisodeRecord]:
        started = time.monotonic()
        observation, info = self.env.reset(options={"start_set": "train"})
        state = self.network.initial_state(1)
        buffer = EpisodeBuffer(frames=[observation])
        terminated = truncated = collided = False
        while not (terminated or truncated or stop.is_set()):
            self.apply_mail()
            if self.uses_network():
                q_values, state = self.q_values(observation, state)
                action = self.strategy.act(q_values, self.rng)
            else:
                action = int(self.rng.integers(self.config.network.n_actions))
            observation, reward, terminated, truncated, info = self.env.step(action)
            collided = collided or bool(info.get("collision", False))
            buffer.frames.append(observation)
            buffer.actions.append(action)
            buffer.rewards.append(float(reward))
            buffer.versions.append(self.weights_version)
        return self._finish(buffer, terminated, truncated, collided, info, time.monotonic() - started)

    @torch.inference_mode()
    def q_values(self, observation: np.ndarray, state):
        frame = torch.from_numpy(observation).view(1, 1, *observation.shape)
        q_values, state = self.network(frame, state)
        return q_values[0, 0].numpy(), state

    def _finish(self, buffer: EpisodeBuffer, terminated: bool, truncated: bool, collided: bool,
                info: dict, wall_time: float) -> tuple[Episode, EpisodeRecord]:
        epsilon = float(self.strategy.epsilon) if self.uses_network() else 1.0
        episode = Episode(
            observations=FrameStack.from_array(np.stack(buffer.frames)),
            actions=np.asarray(buffer.actions, dtype=np.int64),
            rewards=np.asarray(buffer.rewards, dtype=np.float32),
            terminated=bool(terminated),
            truncated=bool(truncated and not terminated),
            actor_id=self.actor_id,
            start_set=str(info.get("start_set", "train")),
            start_index=int(info.get("start_index", -1)),
            weights_version=np.asarray(buffer.versions, dtype=np.int64),
            epsilon=epsilon,
            seed=self.seed,
            episode_index=self.episode_index,
        )
        record = EpisodeRecord(
            actor_id=self.actor_id, episode_index=self.episode_index, length=len(buffer.actions),
            episode_return=float(sum(buffer.rewards)), collided=collided,
            start_set=episode.start_set, start_index=episode.start_index, epsilon=epsilon,
            weights_version=self.weights_version, wall_time=wall_time, time=time.time())
        self.episode_index += 1
        return episode, record


def run_actor(config: Config, max_episodes: int | None = None) -> None:
    """Runs episodes until stopped (SIGINT/SIGTERM) or after max_episodes."""
    actor_id = config.actor.actor_id
    setup_logging(f"actor-{actor_id}")
    torch.set_num_threads(1)  # one core per actor; the learner owns the rest
    stop = threading.Event()
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda *_: stop.set())
    actor = Actor(config, actor_id)
    log.info("actor %d (seed %d), strategy %s until the learner's exploration state says otherwise",
             actor_id, actor.seed, config.exploration.strategy)
    keys = Keys(config.transport.namespace, config.run.name)
    session = open_session(config.transport)
    try:
        liveliness = declare_liveliness(session, keys.liveliness("actor", str(actor_id)))
        subscriptions = [subscribe(session, keys.weights, actor.mailbox.offer_weights, expected=Weights),
                         subscribe(session, keys.exploration, actor.mailbox.offer_exploration,
                                   expected=ExplorationState),
                         subscribe(session, keys.replay_rate, actor.mailbox.offer_rate, expected=Stats)]
        episodes_out = publisher(session, keys.episodes)
        records_out = publisher(session, keys.metrics_source("actor", str(actor_id)))
        threading.Thread(target=_fetch_latest_weights, args=(session, keys, actor.mailbox), daemon=True).start()
        _drive(actor, stop, max_episodes, episodes_out, records_out)
    finally:
        session.close()
    log.info("actor %d stopped after %d episodes", actor_id, actor.episode_index)


def _fetch_latest_weights(session, keys: Keys, mailbox: Mailbox) -> None:
    reply = request(session, keys.weights_latest, None, LATEST_WEIGHTS_TIMEOUT_S)
    if isinstance(reply, Weights):
        mailbox.offer_weights(reply)


def _drive(actor: Actor, stop: threading.Event, max_episodes: int | None, episodes_out, records_out) -> None:
    report = Every(actor.config.actor.log_period_s)
    steps = 0
    returns: list[float] = []
    while not stop.is_set() and (max_episodes is None or actor.episode_index < max_episodes):
        if not _replay_allows_next_episode(actor, stop):
            break
        episode, record = actor.run_episode(stop)
        if stop.is_set() and not (episode.terminated or episode.truncated):
            break  # an interrupted episode is not a real one
        if not _replay_listening(episodes_out, stop):
            break
        episodes_out.put(episode)
        records_out.put(record)
        steps += record.length
        returns.append(record.episode_return)
        if report.due():
            log.info("episodes %d, steps %d, mean return %.2f, weights v%d, epsilon %.3f",
                     actor.episode_index, steps, float(np.mean(returns)), actor.weights_version, record.epsilon)
            returns.clear()


def _replay_listening(episodes_out, stop: threading.Event) -> bool:
    """Zenoh drops a put that no subscriber matches, so an episode waits for the replay."""
    waiting = Every(REPLAY_WAIT_LOG_S)
    while not episodes_out.matched:
        if stop.wait(0.1):
            return False
        if waiting.due():
            log.warning("no replay is subscribed to episodes; holding the finished episode")
    return True


def _replay_allows_next_episode(actor: Actor, stop: threading.Event) -> bool:
    """Waits at an episode boundary while the replay's rate limiter says hold; False if stopped."""
    waiting = Every(actor.config.actor.log_period_s)
    started = time.monotonic()
    while reason := actor.mailbox.must_hold():
        if stop.wait(0.01):
            return False
        if waiting.due():
            why = "the run's step budget is spent" if reason == "budget" else "the learner is behind"
            log.info("holding the next episode: %s (%.0fs so far)", why, time.monotonic() - started)
    return True
