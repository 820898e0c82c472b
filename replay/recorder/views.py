"""JSON copies of wire messages that Foxglove decodes without plugins.

A view channel has message encoding ``json`` and a JSON Schema (schema encoding
``jsonschema``). Its topic is ``/view/`` plus the key relative to the run:
``/view/metrics/learner/0`` (learner Stats, values flattened so a plot path reads
``/view/metrics/learner/0.loss``), ``/view/replay/stats``, ``/view/exploration``,
``/view/metrics/actor/0`` (EpisodeRecords).

An Episode becomes what the car saw: its frames on ``/view/camera/actor/<id>``
(``foxglove.CompressedImage``, base64 PNG or JPEG) and one record per step on
``/view/steps/actor/<id>`` (action, reward, return so far, epsilon, weights
version), each at the time its frame was seen. An episode is published when it
ends, so its frames are laid out backwards from that moment, one decision period
apart, squeezed when needed so they never overlap the actor's previous episode.
JSON has no NaN: non-finite numbers become null.
"""

from __future__ import annotations

import base64
import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from common.wire.codecs import Dependent, Flag, Integer, Message, NumberDict, Real, Text, pack_fields
from common.wire.envelope import decode
from common.wire.errors import WireError
from common.wire.exploration_state import Record
from common.wire.messages import COUNTER_TYPES, Episode, EpisodeRecord, ExplorationState, Stats, flat_values
from replay.recorder.arrival import relative_key

VIEW_ENCODING = "json"
SCHEMA_ENCODING = "jsonschema"
VIEW_PREFIX = "/view/"
IMAGE_SCHEMA_NAME = "foxglove.CompressedImage"  # the name Foxglove's Image panel recognises

_JSON_TYPES = {Integer: "integer", Real: ["number", "null"], Text: "string", Flag: "boolean",
               NumberDict: "object", Record: "object", Dependent: "object"}

TIME_SCHEMA = {"type": "object", "title": "time",
               "properties": {"sec": {"type": "integer", "minimum": 0},
                              "nsec": {"type": "integer", "minimum": 0, "maximum": 999_999_999}}}
IMAGE_SCHEMA = {
    "title": IMAGE_SCHEMA_NAME, "type": "object",
    "properties": {"timestamp": TIME_SCHEMA, "frame_id": {"type": "string"},
                   "data": {"type": "string", "contentEncoding": "base64"}, "format": {"type": "string"}},
    "required": ["timestamp", "frame_id", "data", "format"],
}
STEP_SCHEMA = {
    "title": "d3rqn.Step", "type": "object",
    "properties": {name: {"type": kind} for name, kind in (
        ("actor_id", "integer"), ("episode_index", "integer"), ("step", "integer"), ("action", "integer"),
        ("reward", "number"), ("return", "number"), ("epsilon", "number"), ("weights_version", "integer"))},
}


@dataclass(frozen=True)
class View:
    topic: str
    schema_name: str
    schema: dict
    log_ns: int
    value: dict


def message_schema(cls: type[Message]) -> dict:
    """The JSON Schema of a message's plain fields, from their codecs."""
    properties = {}
    for f in dataclasses.fields(cls):
        kind = next((kind for codec, kind in _JSON_TYPES.items() if isinstance(f.metadata["codec"], codec)), None)
        if kind is not None:
            properties[f.name] = {"type": kind}
    return {"title": f"d3rqn.{cls.__name__}", "type": "object", "properties": properties}


def counters_schema(cls: type[Message]) -> dict:
    """A counters message flattened (common/wire/messages.py flat_values): its time and named numbers."""
    return {"title": f"d3rqn.{cls.__name__}", "type": "object",
            "properties": {"source": {"type": "string"}, "time": {"type": "number"}},
            "additionalProperties": {"type": ["number", "string", "null"]}}


SCHEMAS = {**{cls: counters_schema(cls) for cls in COUNTER_TYPES}, EpisodeRecord: message_schema(EpisodeRecord),
           ExplorationState: message_schema(ExplorationState)}
VIEWED_TYPES = frozenset(cls.__name__ for cls in SCHEMAS)


def json_safe(value: Any) -> Any:
    """The value with numpy scalars unwrapped and non-finite floats as None."""
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {str(key): json_safe(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(item) for item in value]
    return value


def message_view(message: Message) -> dict:
    """A counters message, EpisodeRecord or ExplorationState as a JSON object (counters flattened)."""
    if isinstance(message, Stats):
        return json_safe({**message.values, "source": message.source, "time": message.time})
    if isinstance(message, COUNTER_TYPES):
        return json_safe(flat_values(message))
    fields = pack_fields(message, type(message).__name__)  # the wire form: typed parts as plain maps
    return json_safe({name: fields[name] for name in SCHEMAS[type(message)]["properties"]})


def frame_times_ns(frames: int, end_ns: int, previous_end_ns: int | None, period_ns: int) -> list[int]:
    """When each of an episode's frames was seen: the last at end_ns, one period apart, all after previous_end_ns."""
    spacing = period_ns
    if previous_end_ns is not None and end_ns > previous_end_ns:
        spacing = min(period_ns, (end_ns - previous_end_ns) // frames)
    return [end_ns - (frames - 1 - index) * spacing for index in range(frames)]


def encode_image(frame: np.ndarray, image_format: str) -> bytes:
    import cv2  # only the image views need OpenCV
    ok, encoded = cv2.imencode(f".{image_format}", cv2.cvtColor(frame, cv2.COLOR_RGB2BGR))
    if not ok:
        raise WireError(f"cannot encode a frame of shape {frame.shape} as {image_format}")
    return encoded.tobytes()


def image_view(topic: str, frame: np.ndarray, log_ns: int, frame_id: str, image_format: str) -> View:
    data = base64.b64encode(encode_image(frame, image_format)).decode("ascii")
    stamp = {"sec": log_ns // 1_000_000_000, "nsec": log_ns % 1_000_000_000}
    return View(topic, IMAGE_SCHEMA_NAME, IMAGE_SCHEMA, log_ns,
                {"timestamp": stamp, "frame_id": frame_id, "data": data, "format": image_format})


class ViewMaker:
    """Turns recorded wire messages into views; remembers each actor's previous episode end."""

    def __init__(self, run_root: str, decision_period_s: float, images: bool, image_format: str = "png") -> None:
        self.run_root = run_root
        self.period_ns = round(decision_period_s * 1e9)
        self.images = images
        self.image_format = image_format
        self._previous_end: dict[int, int] = {}

    def wants(self, message_type: str | None) -> bool:
        """Whether a message of this type has views; checked first, so no Weights is ever decoded here."""
        return message_type in VIEWED_TYPES or (self.images and message_type == Episode.__name__)

    def views(self, key: str, data: bytes, log_ns: int) -> list[View]:
        """The views of one recorded message; none for other types or a malformed message."""
        try:
            message = decode(data)
        except WireError:
            return []
        topic = VIEW_PREFIX + relative_key(self.run_root, key)
        if type(message) in SCHEMAS:
            schema = SCHEMAS[type(message)]
            return [View(topic, schema["title"], schema, log_ns, message_view(message))]
        if isinstance(message, Episode) and self.images:
            try:
                return self.episode_views(message, log_ns)
            except WireError:  # a frame that does not decompress: the episode has no views
                return []
        return []

    def episode_views(self, episode: Episode, end_ns: int) -> list[View]:
        actor = episode.actor_id
        frames = episode.observations.decode()
        times = frame_times_ns(len(frames), end_ns, self._previous_end.get(actor), self.period_ns)
        self._previous_end[actor] = end_ns
        camera, steps = f"{VIEW_PREFIX}camera/actor/{actor}", f"{VIEW_PREFIX}steps/actor/{actor}"
        returns = np.cumsum(episode.rewards, dtype=np.float64)
        views = []
        for index, (frame, time_ns) in enumerate(zip(frames, times)):
            views.append(image_view(camera, frame, time_ns, f"actor{actor}/camera", self.image_format))
            if index > 0:  # frame i is what step i - 1 led to
                step = index - 1
                views.append(View(steps, STEP_SCHEMA["title"], STEP_SCHEMA, time_ns, json_safe({
                    "actor_id": actor, "episode_index": episode.episode_index, "step": step,
                    "action": episode.actions[step], "reward": episode.rewards[step], "return": returns[step],
                    "epsilon": episode.epsilon, "weights_version": episode.weights_version[step]})))
        return views
