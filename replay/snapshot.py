"""The replay's snapshot: its episodes and counters on disk, written incrementally, restored on resume.

Layout of ``<runs_dir>/<run>/replay/snapshot/``:

- ``segment-<n>.bin``: episodes, each written once, by the first snapshot after it
  arrived. A record is a little-endian header (payload length, CRC-32 of the payload)
  and a msgpack payload (insertion number, frame shape, the compressed frame blobs as
  they arrived, actions, rewards, weights versions, terminal flag, and the LSTM state
  rows of a run with learner.stored_state: float16 bytes and their unit count);
- ``manifest.msgpack``: which records are live (insertion number, segment, offset,
  length) and the counters: the store's, the rate limiter's and the episode ledger's.

A snapshot writes the episodes new since the last one into a new segment, syncs it,
then replaces the manifest atomically (a temporary file renamed over it, the directory
synced): a replay killed at any moment leaves the previous manifest or the new one,
never a mix. Segments whose episodes were all evicted are deleted after the manifest
no longer names them; eviction is oldest-first, so segments die whole, in order.

The caller takes the view (the list of stored episodes, which never change once
stored, and copies of the counters) under its lock, which is a moment's work; all
writing happens outside it.
"""

from __future__ import annotations

import logging
import os
import struct
import time
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

import msgpack
import numpy as np

from common.atomic_file import write_atomically
from common.wire.errors import WireError
from common.wire.frames import FrameStack
from replay.store import StoredEpisode

log = logging.getLogger("replay.snapshot")

MANIFEST = "manifest.msgpack"
SEGMENT_PREFIX = "segment-"
SEGMENT_SUFFIX = ".bin"
HEADER = struct.Struct("<II")  # payload length, CRC-32
VERSION = 1


class SnapshotError(RuntimeError):
    """A snapshot cannot be written or its manifest cannot be read."""


@dataclass
class SnapshotView:
    """What one snapshot writes, taken under the replay's lock."""

    episodes: list[StoredEpisode]
    store: dict
    limiter: dict
    ledger: dict
    taken: float = field(default_factory=time.time)  # time.time() of the view


@dataclass
class SnapshotReport:
    episodes: int  # live episodes the manifest names
    written_episodes: int  # of them new in this snapshot
    written_bytes: int  # segment and manifest bytes this snapshot wrote
    total_bytes: int  # the snapshot's size on disk
    seconds: float  # time spent writing


@dataclass
class Restored:
    episodes: list[StoredEpisode]
    store: dict
    limiter: dict
    ledger: dict
    taken: float  # time.time() of the restored snapshot's view
    skipped: int  # records that were damaged or did not fit the run


def _segment_name(number: int) -> str:
    return f"{SEGMENT_PREFIX}{number:08d}{SEGMENT_SUFFIX}"


def _segment_number(path: Path) -> int | None:
    stem = path.name[len(SEGMENT_PREFIX):-len(SEGMENT_SUFFIX)]
    if path.name.startswith(SEGMENT_PREFIX) and path.name.endswith(SEGMENT_SUFFIX) and stem.isdigit():
        return int(stem)
    return None


def _fsync_directory(directory: Path) -> None:
    descriptor = os.open(directory, os.O_RDONLY)
    try:
        os.fsync(descriptor)
    finally:
        os.close(descriptor)


def encode_record(stored: StoredEpisode) -> bytes:
    payload = msgpack.packb({
        "seq": stored.seq, "shape": list(stored.frames.frame_shape), "blobs": stored.frames.blobs,
        "actions": np.ascontiguousarray(stored.actions, "<i8").tobytes(),
        "rewards": np.ascontiguousarray(stored.rewards, "<f4").tobytes(),
        "versions": np.ascontiguousarray(stored.weights_version, "<i8").tobytes(),
        "terminated": bool(stored.terminated),
        **({} if stored.states is None else {"state_units": int(stored.states.shape[2]),
                                              "states": np.ascontiguousarray(stored.states, "<f2").tobytes()}),
    }, use_bin_type=True)
    return HEADER.pack(len(payload), zlib.crc32(payload)) + payload


def decode_record(data: bytes, frame_shape: tuple[int, ...]) -> StoredEpisode:
    """ValueError if the record is damaged or its frames are not of frame_shape."""
    if len(data) < HEADER.size:
        raise ValueError("record shorter than its header")
    length, crc = HEADER.unpack_from(data)
    payload = data[HEADER.size:]
    if len(payload) != length or zlib.crc32(payload) != crc:
        raise ValueError("record length or checksum does not match")
    try:
        record = msgpack.unpackb(payload, raw=False)
        frames = FrameStack(record["blobs"], record["shape"])
        actions = np.frombuffer(record["actions"], "<i8")
        rewards = np.frombuffer(record["rewards"], "<f4")
        versions = np.frombuffer(record["versions"], "<i8")
        seq, terminated = int(record["seq"]), bool(record["terminated"])
        states = _state_rows(record, len(actions))
    except (KeyError, TypeError, ValueError, msgpack.UnpackException) as error:
        raise ValueError(f"malformed record ({error!r})") from None
    if frames.frame_shape != tuple(frame_shape):
        raise ValueError(f"frames of shape {list(frames.frame_shape)}, the run's are {list(frame_shape)}")
    if not (len(actions) == len(rewards) == len(versions) == len(frames) - 1 >= 1):
        raise ValueError("record's arrays do not match its frames")
    try:
        frames.check_headers()
    except WireError as error:
        raise ValueError(str(error)) from None
    return StoredEpisode.of(frames, actions, rewards, versions, terminated, seq, states)


def _state_rows(record: dict, steps: int) -> np.ndarray | None:
    """A record's LSTM state rows [steps, 2, units], or None if it has none; ValueError if they are damaged."""
    if "states" not in record:
        return None
    units = int(record["state_units"])
    rows = np.frombuffer(record["states"], "<f2")
    if units < 1 or rows.size != steps * 2 * units or not np.isfinite(rows).all():
        raise ValueError(f"state rows of {rows.size} values do not fill {steps} steps of 2 x {units}")
    return rows.reshape(steps, 2, units)


class Snapshotter:
    """Writes and reads one snapshot directory; one writer at a time."""

    def __init__(self, directory: Path) -> None:
        self.directory = Path(directory)
        self._locations: dict[int, tuple[int, int, int]] = {}  # seq -> segment, offset, length
        self._segment_bytes: dict[int, int] = {}
        self._next_segment = 0
        self.manifest_bytes = 0

    @property
    def exists(self) -> bool:
        return (self.directory / MANIFEST).exists()

    def clear(self) -> None:
        """Removes an earlier snapshot (a fresh start of the run)."""
        if not self.directory.exists():
            return
        for path in self.directory.iterdir():
            if path.name == MANIFEST or _segment_number(path) is not None or path.name.endswith(".tmp"):
                path.unlink(missing_ok=True)
        self._locations, self._segment_bytes, self._next_segment = {}, {}, 0

    # --- writing --------------------------------------------------------------------------

    def write(self, view: SnapshotView) -> SnapshotReport:
        """Writes the episodes the directory lacks, then the manifest; raises SnapshotError (the
        previous snapshot stays whole)."""
        started = time.monotonic()
        try:
            self.directory.mkdir(parents=True, exist_ok=True)
            new = [stored for stored in view.episodes if stored.seq not in self._locations]
            written = self._write_segment(new) if new else 0
            live = {stored.seq for stored in view.episodes}
            manifest = msgpack.packb({
                "version": VERSION, "taken": view.taken, "next_segment": self._next_segment,
                "episodes": [[seq, *self._locations[seq]] for seq in sorted(live)],
                "store": view.store, "limiter": view.limiter, "ledger": view.ledger,
            }, use_bin_type=True)
            write_atomically(self.directory / MANIFEST, lambda handle: handle.write(manifest))
            _fsync_directory(self.directory)
        except OSError as error:
            raise SnapshotError(f"cannot write the snapshot in {self.directory}: {error}") from None
        self.manifest_bytes = len(manifest)
        self._forget_dead(live)
        return SnapshotReport(len(live), len(new), written + len(manifest), self.total_bytes,
                              time.monotonic() - started)

    @property
    def total_bytes(self) -> int:
        return sum(self._segment_bytes.values()) + self.manifest_bytes

    def _write_segment(self, episodes: list[StoredEpisode]) -> int:
        number = self._next_segment
        path = self.directory / _segment_name(number)
        offset = 0
        locations = {}
        try:
            with open(path, "wb") as handle:
                for stored in episodes:
                    record = encode_record(stored)
                    handle.write(record)
                    locations[stored.seq] = (number, offset, len(record))
                    offset += len(record)
                handle.flush()
                os.fsync(handle.fileno())
        except OSError:  # no manifest names it: a part left behind would only hold space
            path.unlink(missing_ok=True)
            raise
        self._next_segment += 1
        self._locations.update(locations)
        self._segment_bytes[number] = offset
        return offset

    def _forget_dead(self, live: set[int]) -> None:
        for seq in [seq for seq in self._locations if seq not in live]:
            del self._locations[seq]
        used = {segment for segment, _, _ in self._locations.values()}
        for number in [number for number in self._segment_bytes if number not in used]:
            del self._segment_bytes[number]
            try:
                (self.directory / _segment_name(number)).unlink(missing_ok=True)
            except OSError as error:
                log.warning("cannot remove the dead snapshot segment %s: %s", _segment_name(number), error)

    # --- reading --------------------------------------------------------------------------

    def load(self, frame_shape: tuple[int, ...]) -> Restored | None:
        """The snapshot's episodes and counters, None if there is none; SnapshotError if its
        manifest is unreadable. A damaged record or one of another frame shape is skipped and
        counted; segments the manifest does not name (a snapshot cut short) are removed."""
        path = self.directory / MANIFEST
        try:
            data = path.read_bytes()
        except FileNotFoundError:
            return None
        except OSError as error:
            raise SnapshotError(f"cannot read {path}: {error}") from None
        try:
            manifest = msgpack.unpackb(data, raw=False)
            if manifest["version"] != VERSION:
                raise ValueError(f"snapshot version {manifest['version']!r}, expected {VERSION}")
            entries = [(int(seq), int(segment), int(offset), int(length))
                       for seq, segment, offset, length in manifest["episodes"]]
            store, limiter, ledger = dict(manifest["store"]), dict(manifest["limiter"]), dict(manifest["ledger"])
            taken, next_segment = float(manifest["taken"]), int(manifest["next_segment"])
        except (KeyError, TypeError, ValueError, msgpack.UnpackException) as error:
            raise SnapshotError(f"{path} is not a replay snapshot manifest ({error})") from None
        episodes, skipped = self._read_records(entries, frame_shape)
        self._next_segment = max([next_segment, *(s + 1 for s in self._segments_on_disk())])
        self.manifest_bytes = len(data)
        self._forget_dead({stored.seq for stored in episodes})
        for number in self._segments_on_disk():
            if number not in self._segment_bytes:
                (self.directory / _segment_name(number)).unlink(missing_ok=True)
        return Restored(episodes, store, limiter, ledger, taken, skipped)

    def _read_records(self, entries, frame_shape) -> tuple[list[StoredEpisode], int]:
        episodes, skipped, handles = [], 0, {}
        try:
            for seq, segment, offset, length in entries:
                try:
                    handle = handles.get(segment)
                    if handle is None:
                        handle = handles[segment] = open(self.directory / _segment_name(segment), "rb")
                        self._segment_bytes[segment] = os.fstat(handle.fileno()).st_size
                    handle.seek(offset)
                    stored = decode_record(handle.read(length), frame_shape)
                    if stored.seq != seq:
                        raise ValueError(f"record holds episode {stored.seq}, the manifest says {seq}")
                except (OSError, ValueError) as error:
                    skipped += 1
                    log.warning("snapshot: skipped episode %d (segment %d): %s", seq, segment, error)
                    continue
                episodes.append(stored)
                self._locations[seq] = (segment, offset, length)
        finally:
            for handle in handles.values():
                handle.close()
        return episodes, skipped

    def _segments_on_disk(self) -> list[int]:
        if not self.directory.exists():
            return []
        return sorted(number for path in self.directory.iterdir() if (number := _segment_number(path)) is not None)


class Held(NamedTuple):
    episodes: int  # the episodes the manifest names live
    bytes: int  # their records' bytes: the stored episodes' size, which a resumed replay holds in memory


def manifest_held(directory: Path) -> Held | None:
    """What the snapshot in `directory` names (what a replay resumed now restores, less any damaged record);
    None without a readable manifest. Reads the manifest only."""
    try:
        manifest = msgpack.unpackb((Path(directory) / MANIFEST).read_bytes(), raw=False)
        entries = manifest["episodes"]
        return Held(len(entries), sum(int(entry[3]) for entry in entries))
    except (OSError, KeyError, TypeError, ValueError, IndexError, msgpack.UnpackException):
        return None
