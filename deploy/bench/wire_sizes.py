"""Encoded size of every wire message, frame compression, and Episode encode/decode time.

By default the frames are SYNTHETIC (a smooth sky/grass image with a grey road,
dashed lane marks that move with the step, and gaussian pixel noise, --noise); real renderings
are flat-shaded and compress better. Measure real frames with
``--frames-from frames.npy`` (uint8 [n, H, W, C], n >= 2).

    .venv/bin/python deploy/bench/wire_sizes.py [--steps 100] [--frames-from PATH.npy]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import zstandard

from common.config import NetworkConfig
from common.cpu_capability import describe_cpu
from common.exploration.base import Counters
from common.exploration.bmc import BmcConfig, BmcPosterior
from common.wire.envelope import decode, encode
from common.wire.frames import ZSTD_LEVEL, FrameStack
from common.wire.messages import (Episode, EpisodeRecord, ExplorationState, RateState, TraceBatch,
                                  TraceBatchRequest, Weights)
from common.wire.metrics import LearnerStats


def synthetic_frames(count: int, height: int, width: int, noise: float, seed: int = 0) -> np.ndarray:
    """Road-like uint8 frames [count, H, W, 3]: gradient sky and grass, a curving grey road, moving lane dashes, noise."""
    rng = np.random.default_rng(seed)
    rows = np.arange(height)[:, None]
    cols = np.arange(width)[None, :]
    horizon = height // 3
    depth = np.clip((rows - horizon) / (height - horizon), 0.0, 1.0)  # 0 at the horizon, 1 at the bottom
    frames = np.empty((count, height, width, 3), dtype=np.uint8)
    for step in range(count):
        centre = width / 2 + 25 * np.sin(step / 15) * (1 - depth)
        half_width = 4 + 0.45 * width * depth
        offset = np.abs(cols - centre)
        sky = np.array([120.0, 160.0, 220.0]) + rows[..., None] * 0.8
        grass = np.array([60.0, 130.0, 50.0]) + depth[..., None] * 30
        image = np.broadcast_to(np.where((rows < horizon)[..., None], sky, grass), (height, width, 3)).copy()
        road = (rows >= horizon) & (offset < half_width)
        image[road] = [90, 90, 95]
        dashes = road & (offset < 1 + 0.02 * width * depth) & (((rows + 2 * step) // 6) % 2 == 0)
        image[dashes] = [230, 230, 230]
        image = image + rng.normal(0.0, noise, image.shape)
        frames[step] = np.clip(image, 0, 255).astype(np.uint8)
    return frames


def d3rqn_tensors(network: NetworkConfig, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """Random float32 tensors with the D3RQN's parameter shapes (docs/method.md, "The network"), to size a
    Weights message."""
    lstm_in = 64 * 4 * 21  # conv 3 output for a 66 x 200 input
    units = network.lstm_units
    shapes = {
        "conv1.weight": (32, network.frame_channels, 8, 8),
        "conv2.weight": (64, 32, 4, 4),
        "conv3.weight": (64, 64, 3, 3),
        "lstm.weight_ih": (4 * units, lstm_in),
        "lstm.weight_hh": (4 * units, units),
        "lstm.bias_ih": (4 * units,),
        "lstm.bias_hh": (4 * units,),
        "advantage.weight": (network.n_actions, units // 2),
        "value.weight": (1, units // 2),
    }
    return {name: rng.standard_normal(shape, dtype=np.float32) * 0.01 for name, shape in shapes.items()}


def episode_from(frames: np.ndarray, steps: int, rng: np.random.Generator) -> Episode:
    return Episode(
        observations=FrameStack.from_array(frames[: steps + 1]),
        actions=rng.integers(0, 5, steps), rewards=rng.random(steps, dtype=np.float32),
        terminated=False, truncated=True, actor_id=0, start_set="train", start_index=3,
        weights_version=np.full(steps, 12, dtype=np.int64), epsilon=0.05, seed=1, episode_index=4,
    )


def trace_batch_from(episode: Episode, batch: int, length: int, rng: np.random.Generator) -> TraceBatch:
    """A batch built the way the replay does: from stored blobs, no recompression."""
    starts = rng.integers(0, len(episode) - length + 1, batch)
    rows = [np.arange(start, start + length) for start in starts]
    return TraceBatch(
        request_id=1,
        observations=FrameStack.concat(episode.observations.select(range(start, start + length + 1)) for start in starts),
        actions=np.stack([episode.actions[r] for r in rows]), rewards=np.stack([episode.rewards[r] for r in rows]),
        terminated=np.zeros((batch, length), dtype=bool), weights_version=np.stack([episode.weights_version[r] for r in rows]),
        env_steps_total=123_456, episodes_stored=1000,
    )


def small_messages() -> list:
    now = time.time()
    return [
        TraceBatchRequest(request_id=1, batch_size=10, trace_length=10),
        ExplorationState(strategy="bmc", params=(BmcConfig(),), epsilon=0.31, kappa=0.0, started=True,
                         counters=Counters(env_steps=120_000, updates=30_000, returns=90_000),
                         state=BmcPosterior(alpha=31.2, beta=68.9, count=90_000, mean=12.5, m2=4_000.0)),
        LearnerStats(time=now, updates=30_000, env_steps=148_000, loss=0.0123, epsilon=0.31, updates_per_s=4.6,
                     data_wait_share=0.1, weights_version=29_950, precision="float32", update_path="fused"),
        EpisodeRecord(actor_id=2, episode_index=40, length=812, episode_return=640.5, collided=True, start_set="train",
                      start_index=7, epsilon=0.05, weights_version=311, wall_time=41.0, time=now),
        RateState(time=now, env_steps=148_000, batches_served=30_000, updates_due=30_000.0, start_env_steps=28_000.0,
                  hold_reason="", closed=False, refilling=False, refill_env_steps=0, lost_updates=0,
                  recounted_updates=0, error_buffer_updates=50.0, hold_updates=1_500.0,
                  env_steps_per_update_target=4.0, env_steps_per_update=4.0),
    ]


def mean_seconds(function, repeats: int) -> float:
    start = time.perf_counter()
    for _ in range(repeats):
        function()
    return (time.perf_counter() - start) / repeats


def report_compression(frames: np.ndarray) -> None:
    raw = frames[0].nbytes
    print(f"per frame: raw {raw} bytes {frames.shape[1:]}")
    for level in sorted({1, 3, ZSTD_LEVEL}):
        compressor = zstandard.ZstdCompressor(level=level, write_checksum=True)
        blobs = [compressor.compress(np.ascontiguousarray(frame)) for frame in frames]
        seconds = mean_seconds(lambda: [compressor.compress(np.ascontiguousarray(f)) for f in frames], 3) / len(frames)
        size = np.mean([len(blob) for blob in blobs])
        chosen = "  <- used" if level == ZSTD_LEVEL else ""
        print(f"  zstd level {level}: {size:8.0f} bytes ({raw / size:5.1f}x smaller), {seconds * 1e6:6.0f} us/frame{chosen}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps", type=int, default=100, help="episode length (default 100)")
    parser.add_argument("--frames-from", type=Path, help="uint8 frames [n, H, W, C] saved with numpy.save")
    parser.add_argument("--noise", type=float, default=1.0, help="std of the pixel noise of synthetic frames (default 1)")
    parser.add_argument("--repeats", type=int, default=20)
    args = parser.parse_args()
    print(f"CPU: {describe_cpu()}", flush=True)
    rng = np.random.default_rng(0)
    network = NetworkConfig()
    if args.frames_from:
        frames = np.load(args.frames_from)
        if frames.dtype != np.uint8 or frames.ndim != 4 or len(frames) < 2:
            parser.error(f"{args.frames_from}: need uint8 frames [n>=2, H, W, C], got {frames.dtype} {frames.shape}")
        print(f"frames: {len(frames)} REAL frames from {args.frames_from}")
    else:
        frames = synthetic_frames(args.steps + 1, network.frame_height, network.frame_width, args.noise)
        print(f"frames: {len(frames)} SYNTHETIC road-like frames with pixel noise std {args.noise} "
              "(flat-shaded real renderings compress better; measure them with --frames-from)")
    steps = min(args.steps, len(frames) - 1)

    report_compression(frames[: steps + 1])
    episode = episode_from(frames, steps, rng)
    trace_length = min(10, steps)
    messages = [episode, trace_batch_from(episode, 10, trace_length, rng),
                Weights(version=1, tensors=d3rqn_tensors(network, rng), created=time.time()), *small_messages()]
    print("\nencoded sizes:")
    for message in messages:
        size = len(encode(message))
        detail = f" ({steps} steps, {size / (steps + 1):.0f} bytes/frame)" if message is episode else ""
        if isinstance(message, Weights):
            detail = f" ({sum(t.size for t in message.tensors.values()):,} float32 parameters)"
        print(f"  {type(message).__name__:18s} {size:>12,} bytes{detail}")

    data = encode(episode)
    print(f"\nEpisode of {steps} steps, mean of {args.repeats} runs:")
    timings = {
        "compress frames (FrameStack.from_array)": lambda: FrameStack.from_array(frames[: steps + 1]),
        "encode": lambda: encode(episode),
        "decode (checks blob headers)": lambda: decode(data, Episode),
        "decode + decompress all frames": lambda: decode(data, Episode).observations.decode(),
    }
    for name, function in timings.items():
        print(f"  {name:40s} {mean_seconds(function, args.repeats) * 1e3:8.2f} ms")


if __name__ == "__main__":
    main()
