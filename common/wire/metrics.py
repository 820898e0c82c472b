"""The roles' own figures as typed messages: the learner's (metrics/learner/0, learner/metrics.py) and each
actor's (metrics/actor_stats/<id>, actor/runner.py), checked on decode like every message.

Senders from before these types wrote both as an untyped Stats (source "learner" or "actor", a dict of
values); ``from_values`` reads such values into the typed message, so that the logs they recorded still
read (common/wire/envelope.py). A field added after the first senders has a default, which stands for
it in their messages.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any, ClassVar

from common.wire.codecs import (COUNT, PROBABILITY, Codec, Counts, Flag, Integer, Message, Nullable, Real, Text,
                                unpack_fields, wired)

# A figure measured over a report's updates: NaN when none was measured in it, and a diverged loss is
# reported as it is (the log line warns), so not finite either.
FIGURE = Real(min_value=0.0, finite=False)
NOT_MEASURED = math.nan
VERSION = Integer(min_value=-1)  # a weights version; -1: none yet
# Counters named at run time (rejected_<kind>, malformed_<door>, rejected_total): a mapping, each a count.
REJECTED_PREFIXES = ("rejected_", "malformed_")


@dataclass(eq=False)
class LearnerStats(Message):
    """The learner's figures, every learner.log_period_s and once more as it stops (final)."""

    former_types: ClassVar[tuple[str, ...]] = ("Stats",)
    time: float = wired(Real())
    updates: int = wired(COUNT)
    env_steps: int = wired(COUNT)
    loss: float = wired(FIGURE)  # mean over the report's updates
    epsilon: float = wired(PROBABILITY)
    updates_per_s: float = wired(Real(min_value=0.0))
    data_wait_share: float = wired(Real(min_value=0.0))  # waiting for a batch: the replay holds replies
    weights_version: int = wired(VERSION)
    # the paper's training figure: |loss_k - loss_k-1| of consecutive updates, averaged over the report
    loss_abs_diff: float = wired(FIGURE, default=NOT_MEASURED)
    # the gradient's global norm before any clip (learner.grad_clip_norm is chosen from these)
    grad_norm: float = wired(FIGURE, default=NOT_MEASURED)
    grad_norm_max: float = wired(FIGURE, default=NOT_MEASURED)
    kappa: float = wired(Real(min_value=0.0), default=0.0)  # 0: exploring actions are uniform
    bmc_observations: int = wired(COUNT, default=0)
    failed_updates: int = wired(COUNT, default=0)
    checkpoints_failed: int = wired(COUNT, default=0)  # not written: a full disk, say
    # what the updates actually ran ("auto" resolves on the first batch, learner/update.py); "": not stated
    precision: str = wired(Text(), default="")
    update_path: str = wired(Text(), default="")
    sessions_reopened: int = wired(COUNT, default=0)
    hub_silent_s: float = wired(Real(min_value=0.0), default=0.0)
    # the whole run's ratio from the replay's start mark; None before updates start
    env_steps_per_update: float | None = wired(Nullable(Real(min_value=0.0)), default=None)
    start_env_steps: float | None = wired(Nullable(Real(min_value=0.0)), default=None)
    rejected: dict[str, int] = wired(Counts(), default_factory=dict)
    final: bool = wired(Flag(), default=False)  # the last report, sent as the learner stops


@dataclass(eq=False)
class ActorStats(Message):
    """An actor's counters, every actor.log_period_s and once more as it stops."""

    former_types: ClassVar[tuple[str, ...]] = ("Stats",)
    time: float = wired(Real())
    episodes: int = wired(COUNT)  # ended so far
    # its delivery's counters (actor/delivery.py)
    episodes_sent: int = wired(COUNT, default=0)
    episodes_resent: int = wired(COUNT, default=0)
    episodes_kept: int = wired(COUNT, default=0)
    episodes_refused: int = wired(COUNT, default=0)
    episodes_released: int = wired(COUNT, default=0)
    episodes_dropped: int = wired(COUNT, default=0)
    episode_send_failures: int = wired(COUNT, default=0)
    episodes_queued: int = wired(COUNT, default=0)
    episodes_in_flight: int = wired(COUNT, default=0)
    acks_foreign: int = wired(COUNT, default=0)
    weights_version: int = wired(VERSION, default=-1)
    weights_behind: int = wired(COUNT, default=0)  # updates behind the learner's latest
    weights_behind_max: int = wired(COUNT, default=0)
    weights_superseded: int = wired(COUNT, default=0)
    weights_downloads: int = wired(COUNT, default=0)  # actor.weights_download: downloads completed
    weights_download_s: float = wired(Real(min_value=0.0), default=0.0)  # how long the last one took
    sessions_reopened: int = wired(COUNT, default=0)
    hub_silent_s: float = wired(Real(min_value=0.0), default=0.0)
    rejected: dict[str, int] = wired(Counts(), default_factory=dict)


STATS_SUCCESSORS: dict[str, type[Message]] = {"learner": LearnerStats, "actor": ActorStats}  # by Stats source


def from_values(cls: type[Message], time: float, values: dict[str, Any]) -> Message:
    """The typed message of an older sender's Stats values: each field's value by its name, the run-time
    counters into ``rejected``, a flag from its 0 or 1; values of no field (figures since dropped) are left
    out. WireError for a value its field's codec refuses, or a field without default that is missing."""
    fields: dict[str, Any] = {"time": time}
    codecs = {field.name: field.metadata["codec"] for field in dataclasses.fields(cls)}
    for name, value in values.items():
        if name.startswith(REJECTED_PREFIXES) and "rejected" in codecs:
            fields.setdefault("rejected", {})[name] = value
        elif name in codecs and name != "time":
            fields[name] = _packed(codecs[name], value, f"{cls.__name__}.{name}")
    if "rejected" in fields:
        fields["rejected"] = codecs["rejected"].pack(fields["rejected"], f"{cls.__name__}.rejected")
    return unpack_fields(cls, fields, f"{cls.__name__} (from Stats)")


def _packed(codec: Codec, value: Any, where: str) -> Any:
    """An old value in the wire form of its field: an integral number where a float goes, 0 or 1 for a flag."""
    inner = codec.inner if isinstance(codec, Nullable) else codec
    if isinstance(inner, Flag) and value in (0, 1) and not isinstance(value, bool):
        value = value == 1
    return codec.pack(value, where)

