"""Zenoh shared memory for large payloads (weights): a pool sized on first use, with the network path
as the fallback (``transport.shared_memory``).
"""

from __future__ import annotations

import logging
from typing import Any

import zenoh

from common.config import TransportConfig

log = logging.getLogger(__name__)

SHARED_MEMORY_MESSAGES = 3  # the pool holds this many: one being written while subscribers still read older ones


class SharedMemory:
    """A pool of Zenoh shared memory that payloads are put from (zenoh.shm, unstable in zenoh-python 1.x).

    Sized on first use for SHARED_MEMORY_MESSAGES payloads of that size. Where Zenoh has no shared
    memory (a build without it, no room in /dev/shm) or an allocation fails (subscribers still hold
    the whole pool), the payload goes over the network instead, and the first time says so in one
    log line. ``shared`` and ``fallbacks`` count the payloads of each path."""

    def __init__(self) -> None:
        self._provider: Any = None
        self._pool_bytes = 0
        self._warned = False
        self.shared = 0
        self.fallbacks = 0

    @classmethod
    def of(cls, config: TransportConfig) -> SharedMemory | None:
        """A pool when the transport uses shared memory, else None."""
        return cls() if config.shared_memory else None

    def payload(self, data: bytes) -> zenoh.ZBytes | bytes:
        """data copied into a shared-memory buffer, or data itself when there is none to have."""
        try:
            buffer = self._allocate(len(data))
            buffer[:] = data
        except Exception as error:  # no zenoh.shm, no room, a pool in use: the network path
            self.fallbacks += 1
            if not self._warned:
                self._warned = True
                log.warning("shared memory unavailable (%s: %s): messages of %.1f MB go over the network",
                            type(error).__name__, error, len(data) / 1e6)
            return data
        self.shared += 1
        return zenoh.ZBytes(buffer)

    def _allocate(self, size: int):
        from zenoh import shm  # ModuleNotFoundError when zenoh is built without shared memory

        if size * SHARED_MEMORY_MESSAGES > self._pool_bytes:  # first use, or larger messages than before
            self._pool_bytes = size * SHARED_MEMORY_MESSAGES
            self._provider = shm.ShmProvider.default_backend(self._pool_bytes)
        return self._provider.alloc(size, shm.GarbageCollect())  # frees buffers no one reads any more, then retries
