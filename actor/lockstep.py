"""The one acting core: N simulators stepped in lockstep, each recording its episode.

Training episodes (the actor, actor/runner.py; the reference loop,
deploy/reference_loop.py) and evaluation episodes (actor/evaluation/) are all
stepped and recorded here, so the two cannot drift apart: the same reset, the
same step, the same end rule, the same record. The caller chooses the actions
(a batched network, a strategy, a baseline; a training episode by ``training_actions``,
the one acting rule) and what to make of an ended episode: ``episode_message``
makes the replay's Episode of a training one.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from common.exploration.base import ExplorationStrategy
from common.wire.frames import FrameStack
from common.wire.messages import Episode
from common.wire.state_rows import no_states


@dataclass
class Trajectory:
    """One simulator's episode so far: its frames (the reset's, then one a step), the actions and rewards,
    one tag a step (the weights version an actor acted on), the caller's LSTM state rows, the last info."""

    frames: list[np.ndarray]
    info: dict
    actions: list[int] = field(default_factory=list)
    rewards: list[float] = field(default_factory=list)
    tags: list[int] = field(default_factory=list)
    states: list[np.ndarray] = field(default_factory=list)  # learner.stored_state: (2, lstm_units) a step
    terminated: bool = False
    truncated: bool = False
    collided: bool = False
    started: float = field(default_factory=time.monotonic)

    @property
    def observation(self) -> np.ndarray:
        return self.frames[-1]

    @property
    def length(self) -> int:
        return len(self.actions)


class Lockstep:
    """Simulators by slot; ``begin`` resets one, ``step`` takes one action in each slot named and returns the
    episodes that ended. An episode ends when the simulator terminates or truncates it, or at max_steps.
    keep_frames=False keeps only the latest frame (an evaluation needs no more, and episodes run long)."""

    def __init__(self, envs: list, max_steps: int | None = None, keep_frames: bool = True) -> None:
        self.envs = envs
        self.max_steps = max_steps
        self.keep_frames = keep_frames
        self.running: dict[int, Trajectory] = {}

    def begin(self, slot: int, seed: int | None = None, options: dict | None = None) -> Trajectory:
        started = time.monotonic()
        observation, info = self.envs[slot].reset(seed=seed, options=options)
        trajectory = Trajectory(frames=[observation], info=info, started=started)
        self.running[slot] = trajectory
        return trajectory

    def step(self, actions: dict[int, int], tag: int = -1) -> list[tuple[int, Trajectory]]:
        """One action in each slot of ``actions`` (running ones), in its order; the ended (slot, episode)s."""
        ended = []
        for slot, action in actions.items():
            trajectory = self.running[slot]
            observation, reward, terminated, truncated, info = self.envs[slot].step(action)
            if not self.keep_frames:
                trajectory.frames.clear()
            trajectory.frames.append(observation)
            trajectory.actions.append(int(action))
            trajectory.rewards.append(float(reward))
            trajectory.tags.append(tag)
            trajectory.info = info
            trajectory.collided = trajectory.collided or bool(info.get("collision", False))
            capped = self.max_steps is not None and trajectory.length >= self.max_steps
            if terminated or truncated or capped:
                trajectory.terminated = bool(terminated)
                trajectory.truncated = not terminated
                ended.append((slot, self.running.pop(slot)))
        return ended


def network_acts(strategy: ExplorationStrategy | None, weights_version: int) -> bool:
    """Whether training acts on the network: once the learner's strategy has started (updates started) and
    weights from the learner came (version >= 0); before, the random phase (no strategy yet: none came)."""
    return strategy is not None and strategy.started and weights_version >= 0


def training_actions(strategy: ExplorationStrategy | None, q_values: np.ndarray | None,
                     rngs: list[np.random.Generator], n_actions: int) -> list[int]:
    """The acting rule of training, which the actor and the reference loop share: uniform at random until the
    network acts (q_values None: not ``network_acts``), then the strategy's rule on each simulator's row of
    Q-values; each draw from that simulator's own generator."""
    if q_values is None:
        return [int(rng.integers(n_actions)) for rng in rngs]
    return [strategy.act(row, rng) for row, rng in zip(q_values, rngs)]


def episode_message(trajectory: Trajectory, *, actor_id: int, seed: int, episode_index: int, epsilon: float,
                    incarnation: int = 0, in_hand: int = 0) -> Episode:
    """The replay's Episode of an ended training episode."""
    info = trajectory.info
    return Episode(
        observations=FrameStack.from_array(np.stack(trajectory.frames)),
        actions=np.asarray(trajectory.actions, dtype=np.int64),
        rewards=np.asarray(trajectory.rewards, dtype=np.float32),
        terminated=trajectory.terminated,
        truncated=trajectory.truncated,
        actor_id=actor_id,
        start_set=str(info.get("start_set", "train")),
        start_index=int(info.get("start_index", -1)),
        weights_version=np.asarray(trajectory.tags, dtype=np.int64),
        epsilon=epsilon,
        seed=seed,
        episode_index=episode_index,
        incarnation=incarnation,
        in_hand=in_hand,
        recurrent_state=np.stack(trajectory.states) if trajectory.states else no_states(),
    )
