"""Every key expression of a run, under ``<namespace>/<run>/``: one place for the names of the keys the
roles talk on (docs/architecture.md lists what travels on each).
"""

from __future__ import annotations

from dataclasses import dataclass


def _check_chunk(text: str, what: str) -> str:
    if not text or any(char in text for char in "/*$?# "):
        raise ValueError(f"{what} {text!r} must be a non-empty key chunk without '/', '*', '$', '?', '#' or spaces")
    return text


@dataclass(frozen=True)
class Keys:
    """Every key expression of one run, all under ``<namespace>/<run>/``."""

    namespace: str
    run: str

    def __post_init__(self) -> None:
        _check_chunk(self.namespace, "namespace")
        _check_chunk(self.run, "run name")

    @property
    def root(self) -> str:
        return f"{self.namespace}/{self.run}"

    @property
    def all(self) -> str:
        """Everything of the run, for a recorder."""
        return f"{self.root}/**"

    @property
    def episodes(self) -> str:
        return f"{self.root}/episodes"

    @property
    def replay_sample(self) -> str:
        """Queryable: TraceBatchRequest -> TraceBatch."""
        return f"{self.root}/replay/sample"

    @property
    def replay_stats(self) -> str:
        return f"{self.root}/replay/stats"

    def episode_acks(self, actor_id: int | None = None) -> str:
        """The replay's EpisodeAcks for one actor (for every actor without one)."""
        return f"{self.root}/replay/acks/{'*' if actor_id is None else _check_chunk(str(actor_id), 'actor id')}"

    @property
    def weights(self) -> str:
        return f"{self.root}/weights/broadcast"

    @property
    def weights_latest(self) -> str:
        """Queryable: (no request) -> the latest Weights."""
        return f"{self.root}/weights/latest"

    @property
    def weights_pieces(self) -> str:
        """Queryable: WeightsPieceAsk -> WeightsPiece (actor.weights_download)."""
        return f"{self.root}/weights/pieces"

    @property
    def exploration(self) -> str:
        return f"{self.root}/exploration"

    @property
    def replay_rate(self) -> str:
        """The replay's rate limiter: env steps, batches served, updates due, whether actors hold."""
        return f"{self.root}/replay/rate"

    def metrics_source(self, role: str, process_id: str | int | None = None) -> str:
        """Metrics of one process: ``metrics/learner``, ``metrics/actor/3``."""
        key = f"{self.root}/metrics/{_check_chunk(role, 'role')}"
        return key if process_id is None else f"{key}/{_check_chunk(str(process_id), 'process id')}"

    @property
    def metrics_all(self) -> str:
        return f"{self.root}/metrics/**"

    def liveliness(self, role: str, process_id: str | int) -> str:
        return f"{self.root}/alive/{_check_chunk(role, 'role')}/{_check_chunk(str(process_id), 'process id')}"

    @property
    def liveliness_all(self) -> str:
        return f"{self.root}/alive/**"
