"""Watch a policy drive: one greedy episode as a video, the front camera (what the network sees) beside a
top-down view of the neighbourhood around the car.

    .venv/bin/python deploy/tools/animate_policy.py --checkpoint results/bmc/policy.pt --start-set test --start 0 \\
        --out /tmp/drive.mp4
    .venv/bin/python deploy/tools/animate_policy.py --checkpoint runs/bmc --start-set train --start 3 --trial 2 \\
        --stride 4 --max-steps 800 --out /tmp/drive.mp4

The episode is the evaluation's (actor/evaluation/episodes.py): the simulator of evaluation_env_config,
reset with the seed of trial --trial of that start (trial_seed, from evaluation.seed), greedy actions of the
float32 network from a zeroed LSTM state; trial 0 of test start 0 is the evaluation's first test episode.
The source is what `evaluate --checkpoint` takes (a kept or shipped policy, a checkpoint, a run folder) and
so is the config: the checkpoint's, changed only by --config FILE and the flags given.

The episode runs until it ends or --max-steps (default: evaluation.max_steps, the cap, 2,000). Every
--stride-th step, and the last, is a frame of 900 x 300: the camera's 66 x 200 frame enlarged 3 times,
pixel for pixel, over a caption (start, step, reward, the steering chosen, progress, how it ended), beside
a heading-up top-down view 48 m across (actor/sim/camera.py's TopDownCamera over the pre-drawn world) with
the car in blue. The .mp4 (OpenCV's mp4v codec) is written as it goes, at VIDEO_BITRATE: its size follows
the video's length, frames / fps; a 2,000-step drive at the defaults (stride 2, 20 fps: 4 times real time,
50 s) is about 3.8 MB. (A GIF was tried: 73 KB a frame, 10 times the MP4.)
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch

from actor.evaluation import EvaluationError
from actor.evaluation.episodes import (EpisodeJob, GreedyPolicy, end_reason, evaluation_env_config, progress_of,
                                       trial_seed)
from actor.evaluation.sources import check_weights, checkpoint_source
from actor.lockstep import Lockstep, Trajectory
from actor.sim import START_SETS, STEERING_LEVELS, make_env, start_poses
from actor.sim.camera import TopDownCamera
from actor.sim.pictures import label
from actor.sim.world_image import world_image
from common.checkpoint import CheckpointError
from common.config import Config
from common.config_cli import add_config_arguments, parse_flags
from common.config_values import to_toml
from common.eta import Eta
from common.network import D3RQN, load_numpy_weights
from common.schema.fields import ConfigError

FRONT_ZOOM = 3  # the 66 x 200 camera frame becomes 198 x 600
CAPTION_ROWS = 102  # below the camera frame: the left column is as tall as the top-down view
TOPDOWN_PX = 300  # the top-down view, square
TOPDOWN_AHEAD_M, TOPDOWN_BEHIND_M, TOPDOWN_WIDTH_M = 34.0, 14.0, 48.0  # 6.25 px/m
INK, PAPER = (20, 20, 20), (255, 255, 255)
VIDEO_BITRATE = 600_000  # bits/s: 3.8 MB for a 2,000-step drive at the default stride and fps
PROGRESS_EVERY_S = 5.0


class AnimationError(RuntimeError):
    """The animation cannot be made as asked."""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="deploy/tools/animate_policy.py",
        description="Drives the greedy policy of a checkpoint or kept policy from one start pose, as the evaluation "
                    "does, and writes a video: the front camera (the network's input) beside a top-down view. "
                    "The config is the checkpoint's, changed only by --config FILE and the flags given.")
    parser.add_argument("--checkpoint", type=Path, required=True, metavar="PATH",
                        help="a kept or shipped policy file, a checkpoint file, or a run folder (its latest "
                             "checkpoint)")
    parser.add_argument("--start-set", choices=START_SETS, default="test", help="start set (default: test)")
    parser.add_argument("--start", type=int, default=0, metavar="N", help="start index in the set (default: 0)")
    parser.add_argument("--trial", type=int, default=0, metavar="N",
                        help="the evaluation's trial of that start whose seed resets the simulator (default: 0)")
    parser.add_argument("--max-steps", type=int, metavar="N",
                        help="stop after this many steps (default: evaluation.max_steps, the episode's cap)")
    parser.add_argument("--stride", type=int, default=2, metavar="K",
                        help="a frame every K steps, and the last step's (default: 2)")
    parser.add_argument("--fps", type=float, default=20.0,
                        help="frames per second of the video (default: 20; at 10 decisions/s and stride 2 that "
                             "plays 4 times real time); the file grows with the video's length, frames / fps")
    parser.add_argument("--out", type=Path, required=True, metavar="FILE", help="the video file (.mp4)")
    add_config_arguments(parser)
    return parser


@dataclass
class Drive:
    """What one animation showed."""

    steps: int  # actions taken
    end: str  # collision, offroad, stalled, cap, or "cut" at --max-steps
    frames: int
    frame_size: tuple[int, int]  # width, height
    progress_m: float
    wall_s: float


class VideoFile:
    """Frames into an .mp4 (OpenCV's mp4v codec) as they come, at VIDEO_BITRATE where OpenCV can set it."""

    def __init__(self, path: Path, fps: float) -> None:
        if path.suffix != ".mp4":
            raise AnimationError(f"--out: the video is an .mp4, not {path.name!r}")
        self.path, self.fps = path, fps
        self.writer: cv2.VideoWriter | None = None
        self.count = 0

    def add(self, rgb: np.ndarray) -> None:
        if self.writer is None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            bitrate = getattr(cv2, "VIDEOWRITER_PROP_BITRATE", None)  # an older OpenCV picks its own, larger
            params = [] if bitrate is None else [bitrate, VIDEO_BITRATE]
            self.writer = cv2.VideoWriter(str(self.path), cv2.CAP_FFMPEG, cv2.VideoWriter_fourcc(*"mp4v"), self.fps,
                                          (rgb.shape[1], rgb.shape[0]), params)
            if not self.writer.isOpened():
                raise AnimationError(f"OpenCV cannot write {self.path} with the mp4v codec")
        self.writer.write(cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        self.count += 1

    def close(self) -> None:
        if self.writer is not None:
            self.writer.release()


def topdown_camera(config: Config) -> TopDownCamera:
    """A wider, square window of the env's own top-down camera, over the same pre-drawn world."""
    env = config.env
    return TopDownCamera(world_image(env.render_scale, env.offroad_distance), TOPDOWN_AHEAD_M, TOPDOWN_BEHIND_M,
                         TOPDOWN_WIDTH_M)


def frame(observation: np.ndarray, topdown: np.ndarray, caption: list[str]) -> np.ndarray:
    """[camera frame enlarged, over the caption | top-down view], RGB."""
    front = cv2.resize(observation, None, fx=FRONT_ZOOM, fy=FRONT_ZOOM, interpolation=cv2.INTER_NEAREST)
    panel = np.full((CAPTION_ROWS, front.shape[1], 3), PAPER, dtype=np.uint8)
    for row, line in enumerate(caption):
        label(panel, line, (10, 24 + 26 * row), INK)
    left = np.vstack([front, panel])
    label(left, "front camera: the network's input", (8, 20), INK)
    right = topdown.copy()
    label(right, "top-down, heading up", (8, 20), INK)
    return np.hstack([left, right])


def caption(job: EpisodeJob, step: int, action: int | None, reward: float | None, progress_m: float,
            end: str | None, max_steer_deg: float) -> list[str]:
    """Three lines: the episode; the step, the reward of the step that led here and the steering chosen now;
    the progress, and how the episode ended."""
    earned = "" if reward is None else f"   reward {reward:.2f}"
    chosen = "" if action is None else f"   now steers {STEERING_LEVELS[action] * max_steer_deg:+.1f} deg"
    progress = "" if math.isnan(progress_m) else f"{progress_m:,.0f} m along the road"
    ended = "" if end is None else f"   ended: {end}"
    return [f"{job.start_set} start {job.start_index}, trial {job.trial}, greedy",
            f"step {step:,}{earned}{chosen}", f"{progress}{ended}"]


def animate(config: Config, weights: dict[str, np.ndarray], job: EpisodeJob, max_steps: int, stride: int,
            video: VideoFile, show_progress: bool = True) -> Drive:
    """Drives the episode of `job` with the greedy policy and writes its frames to `video`."""
    network = D3RQN(config.network)
    load_numpy_weights(network, weights)
    policy = GreedyPolicy(network, 1)
    core = Lockstep([make_env(evaluation_env_config(config))], config.evaluation.max_steps, keep_frames=False)
    sim, camera = core.envs[0].unwrapped, topdown_camera(config)
    started, eta, shown = time.monotonic(), Eta(max_steps), time.monotonic()
    try:
        drive = core.begin(0, seed=job.seed, options={"start_set": job.start_set, "start_index": job.start_index})
        policy.begin(0, job, sim.pose)
        step, reward, end, progress_m, size = 0, None, None, math.nan, (0, 0)
        while True:
            action = None if end is not None else policy.act([0], [drive.observation], [sim.pose])[0]
            if end is not None or step % stride == 0:
                picture = frame(drive.observation,
                                camera.view(*sim.pose, TOPDOWN_PX, TOPDOWN_PX, sim.traffic_rectangles()),
                                caption(job, step, action, reward, progress_m, end, config.env.max_steer_deg))
                video.add(picture)
                size = (picture.shape[1], picture.shape[0])
            if end is not None:
                break
            ended = core.step({0: action})
            step, reward, progress_m = drive.length, drive.rewards[-1], progress_of(drive.info)
            end = _end_of(drive, bool(ended), step >= max_steps, config.evaluation.max_steps)
            eta.update(step)
            if show_progress and time.monotonic() - shown >= PROGRESS_EVERY_S:
                shown = time.monotonic()
                print(f"animate: step {step:,} of at most {max_steps:,}, {video.count:,} frames, "
                      f"{eta.per_s() or 0:.0f} steps/s, at most {eta.text()} left", file=sys.stderr, flush=True)
        video.close()
    finally:
        core.envs[0].close()
    return Drive(step, end, video.count, size, progress_m, time.monotonic() - started)


def _end_of(drive: Trajectory, ended: bool, cut: bool, max_steps: int) -> str | None:
    """Why the drive ends after this step, as the evaluation reads an episode the acting core ended (the
    simulator's own cut is the cap); "cut" where only this video's shorter cap stops it."""
    if ended:
        return end_reason(drive.info, drive.terminated, drive.length, max_steps) or "cap"
    return "cut" if cut else None


def _main(args: argparse.Namespace) -> Drive | None:
    if args.stride < 1 or args.fps <= 0 or (args.max_steps is not None and args.max_steps < 1):
        raise AnimationError("--stride and --max-steps must be >= 1 and --fps > 0")
    poses = start_poses(args.start_set)
    if not 0 <= args.start < len(poses) or args.trial < 0:
        raise AnimationError(f"--start: the {args.start_set} set has starts 0 to {len(poses) - 1}; --trial >= 0")
    video = VideoFile(args.out, args.fps)
    source = checkpoint_source(args.checkpoint, args)
    config = source.config
    if args.dump_config:
        print(to_toml(config), end="")
        return None
    check_weights(config, source.weights)
    max_steps = min(args.max_steps or config.evaluation.max_steps, config.evaluation.max_steps)
    job = EpisodeJob("greedy", args.start_set, args.start, args.trial,
                     trial_seed(config.evaluation.seed, args.start_set, args.start, args.trial))
    print(f"animate: {source.facts['source']}, updates {source.facts['updates']}; {args.start_set} start "
          f"{args.start}, trial {args.trial}, up to {max_steps:,} steps, a frame every {args.stride}",
          file=sys.stderr, flush=True)
    torch.set_num_threads(1)  # a batch of one: more threads only wait (6 times slower beside a training run)
    drive = animate(config, source.weights, job, max_steps, args.stride, video)
    print(f"wrote {args.out}: {drive.frames:,} frames of {drive.frame_size[0]} x {drive.frame_size[1]} at "
          f"{args.fps:g} fps, {args.out.stat().st_size / 1e6:.1f} MB; the episode: {drive.steps:,} steps, ended "
          f"by {drive.end}, {drive.progress_m:,.0f} m along the road ({drive.wall_s:.1f} s)")
    return drive


def main(argv: list[str] | None = None) -> None:
    args = parse_flags(build_parser(), argv)
    try:
        _main(args)
    except (AnimationError, EvaluationError, ConfigError, CheckpointError) as error:
        print(f"animate_policy: error: {error}", file=sys.stderr)
        raise SystemExit(1) from None


if __name__ == "__main__":
    main()
