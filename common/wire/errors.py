"""The one error of the wire: a message cannot be encoded or decoded, or does not fit the run."""

from __future__ import annotations


class WireError(ValueError):
    """A message cannot be encoded or decoded, or does not fit the run; the text names the field
    and the fault, ``kind`` names the fault for counting ("undecodable", "wrong_type", "invalid",
    or a RunShape check's kind such as "frame_shape" or "actions")."""

    def __init__(self, text: str, kind: str = "invalid") -> None:
        super().__init__(text)
        self.kind = kind
