"""An actor's inbox: the newest acceptable weights, exploration state and replay's word, parked by Zenoh
callbacks and read by the driving loop. Nothing is taken on trust: what does not fit is refused and
counted by kind (actor/runner.py's docstring says what each message must be).
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from typing import Callable

import numpy as np

from common.rejections import Rejections
from common.wire.errors import WireError
from common.wire.messages import ExplorationState, RateState, Weights


log = logging.getLogger("actor")


class Mailbox:
    """Holds only the newest acceptable message of each kind; written by callbacks, read by the loop.

    ``shapes`` (tensor name -> shape) is what weights must hold; without it any weights are kept. Once the
    replay's word has come, a silence of ``silence_hold_s`` holds the actor (None: never): the replay
    announces it every stats period, so an actor that hears nothing may no longer hear the hub."""

    def __init__(self, shapes: dict[str, tuple[int, ...]] | None = None,
                 rejections: Rejections | None = None, max_env_steps: int | None = None,
                 silence_hold_s: float | None = None, clock: Callable[[], float] = time.monotonic) -> None:
        self._lock = threading.Lock()
        self._clock = clock
        self._rate_at: float | None = None  # when the last acceptable rate message came
        self.silence_hold_s = silence_hold_s
        self._weights: Weights | None = None
        self._exploration: ExplorationState | None = None
        self._heard_weights = False  # a broadcast arrived: the answer to the start-up ask is older
        self.hold_reason = ""  # the replay's word on the next episode: "behind", "budget" or "" (go)
        self.updates_started = False  # the replay's word: updates have started (and it is not refilling)
        self.heard_rate = threading.Event()  # a rate message was accepted: the replay's word is known
        self.had_weights = threading.Event()  # weights that fit were accepted at least once
        self.shapes = shapes
        self.rejections = rejections or Rejections(log)
        self.max_env_steps = max_env_steps  # counts above it come from no replay of this run
        self.learner_updates = -1  # batches the replay has served, from its rate message: the learner's updates
        self.superseded = 0  # weights replaced by newer ones before the loop loaded them (a slow link queues them)

    def offer_weights(self, message: Weights, key: str = "") -> None:
        """A broadcast: the newest that fits the network replaces what is held."""
        usable = self._usable(message)
        if usable is not None:
            with self._lock:
                self.superseded += self._weights is not None
                self._weights, self._heard_weights = usable, True
            self.had_weights.set()

    def offer_latest(self, message: Weights) -> None:
        """The learner's answer to the start-up ask: kept unless a broadcast came first."""
        usable = self._usable(message)
        if usable is not None:
            with self._lock:
                if not self._heard_weights:
                    self._weights = usable
            self.had_weights.set()

    def _usable(self, message) -> Weights | None:
        """The message with its tensors as float32 if it fits the network, else None (counted). Compact
        weights are widened here, on Zenoh's thread, so the driving loop only loads them."""
        if not isinstance(message, Weights):
            self.rejections.reject("weights_wrong_type", f"a {type(message).__name__} where weights belong")
            return None
        try:
            tensors = message.to_float32()
        except WireError as error:
            self.rejections.reject(error.kind, f"weights version {message.version}: {error}")
            return None
        if self.shapes is not None:
            shapes = {name: np.shape(array) for name, array in tensors.items()}
            if shapes != self.shapes:
                wrong = sorted(set(shapes.items()) ^ set(self.shapes.items()))[:4]
                self.rejections.reject("weights_network", f"weights version {message.version} are for another "
                                                          f"network (names or shapes differ: {wrong} ...)")
                return None
        return dataclasses.replace(message, tensors=tensors, encoding="float32")

    def offer_exploration(self, message: ExplorationState, key: str = "") -> None:
        if not isinstance(message, ExplorationState):
            self.rejections.reject("exploration_wrong_type", f"a {type(message).__name__} on exploration")
            return
        with self._lock:
            self._exploration = message

    def offer_rate(self, message: RateState, key: str = "") -> None:
        """The replay's rate limiter; kept, not taken: the hold is read repeatedly. Anything but a RateState,
        or one counting more env steps than the run can, is refused and the last word stands (the wire
        checked the rest)."""
        if not isinstance(message, RateState):
            self.rejections.reject("rate", f"replay/rate: a {type(message).__name__}, expected a RateState")
            return
        if self.max_env_steps is not None and message.env_steps > self.max_env_steps:
            self.rejections.reject("rate_values", f"replay/rate: {message.env_steps} env steps, more than this run "
                                                  f"can count ({self.max_env_steps})")
            return
        with self._lock:
            self.hold_reason = message.hold_reason
            self.updates_started = message.updates_started
            self.learner_updates = message.batches_served
            self._rate_at = self._clock()
        self.heard_rate.set()

    def silent_s(self) -> float:
        """Seconds since the replay's last acceptable word (0 before the first)."""
        with self._lock:
            return 0.0 if self._rate_at is None else self._clock() - self._rate_at

    def weights_behind(self, version: int) -> int:
        """Updates between the weights acted on and the learner's latest; 0 while either is unknown."""
        with self._lock:
            return max(0, self.learner_updates - version) if version >= 0 and self.learner_updates >= 0 else 0

    def replay_gone(self) -> None:
        """No replay is alive, so none counts the steps: hold until a replay's word comes again."""
        with self._lock:
            self.hold_reason = "replay"

    def must_hold(self, has_policy: bool = True) -> str:
        """Why the next episode must wait ("" when it may start); no word from a replay yet: go. Without
        the learner's policy (has_policy False) it waits too once updates have started ("policy"); after
        silence_hold_s without the replay's word, too ("silent")."""
        silent = self.silence_hold_s is not None and self.silent_s() > self.silence_hold_s
        with self._lock:
            return self.hold_reason or ("silent" if silent else "") or (
                "" if has_policy or not self.updates_started else "policy")

    def take(self) -> tuple[Weights | None, ExplorationState | None]:
        with self._lock:
            taken = (self._weights, self._exploration)
            self._weights = self._exploration = None
            return taken
