"""Pictures of the simulator: the whole map with its start poses, and a strip of camera frames.

    python -m actor.sim.pictures --out deploy/figures

writes ``neighbourhood_map.png`` (roads, parked cars in red, trees, houses,
training starts in blue and test starts in orange, numbered by
``start_index``, each with an arrow along its heading) and
``observation_strip.png`` (consecutive observations of the privileged driver,
oldest first, read left to right then top to bottom).
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import cv2
import numpy as np

from actor.sim import make_env, start_poses
from actor.sim.privileged import PrivilegedDriver
from actor.sim.world_image import PARKED_CAR, world_image
from common.config import EnvConfig

MAP_SCALE = 3.0  # px per metre of the map picture
START_COLOURS = {"train": (30, 110, 255), "test": (255, 140, 0)}  # RGB
STRIP_FRAMES = 12
STRIP_COLUMNS = 3
STRIP_ZOOM = 2
STRIP_START = ("train", 0)


def map_picture(env_config: EnvConfig) -> np.ndarray:
    """RGB map of the neighbourhood with the numbered start poses of both sets."""
    world = world_image(env_config.render_scale, env_config.offroad_distance)
    zoom = MAP_SCALE / world.scale
    picture = cv2.resize(np.ascontiguousarray(world.rgb), None, fx=zoom, fy=zoom,
                         interpolation=cv2.INTER_AREA)
    for start_set, colour in START_COLOURS.items():
        for index, pose in enumerate(start_poses(start_set)):
            centre = world.to_pixels((pose.x, pose.y)) * zoom
            tip = centre + 7 * MAP_SCALE * np.array([math.cos(pose.heading), math.sin(pose.heading)])
            cv2.arrowedLine(picture, _point(centre), _point(tip), colour, 2, cv2.LINE_AA, tipLength=0.35)
            cv2.circle(picture, _point(centre), 5, colour, -1, cv2.LINE_AA)
            _label(picture, str(index), centre + (-4, -10), colour)
    _label(picture, "train starts", (12, 24), START_COLOURS["train"])
    _label(picture, "test starts", (12, 48), START_COLOURS["test"])
    return picture


def drive_frames(env_config: EnvConfig, steps: int, start: tuple[str, int] = STRIP_START,
                 seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Observations (n, 66, 200, 3) and headings (n,) of the privileged driver, n <= steps + 1."""
    env = make_env(env_config, seed=seed)
    observation, _ = env.reset(options={"start_set": start[0], "start_index": start[1]})
    driver = PrivilegedDriver(env_config, seed=seed)
    driver.reset(env.unwrapped.pose)
    frames, headings = [observation], [env.unwrapped.pose[2]]
    for _ in range(steps):
        observation, _, terminated, truncated, _ = env.step(driver.act(env.unwrapped.pose))
        frames.append(observation)
        headings.append(env.unwrapped.pose[2])
        if terminated or truncated:
            break
    env.close()
    return np.stack(frames), np.unwrap(np.array(headings))


def observation_strip(frames: np.ndarray, headings: np.ndarray) -> np.ndarray:
    """``STRIP_FRAMES`` consecutive frames, tiled and enlarged: of the runs in which every
    frame shows a parked car, the one where the car turns most (a swerve or a corner)."""
    shows_car = np.array([(frame == PARKED_CAR).all(axis=-1).sum() >= 20 for frame in frames])
    turning = np.abs(np.diff(headings, prepend=headings[0]))
    best, first = -1.0, 0
    for start in range(len(frames) - STRIP_FRAMES + 1):
        window = slice(start, start + STRIP_FRAMES)
        if shows_car[window].all() and turning[window].sum() > best:
            best, first = turning[window].sum(), start
    tiles = [cv2.resize(frame, None, fx=STRIP_ZOOM, fy=STRIP_ZOOM, interpolation=cv2.INTER_NEAREST)
             for frame in frames[first:first + STRIP_FRAMES]]
    tiles = [cv2.copyMakeBorder(tile, 2, 2, 2, 2, cv2.BORDER_CONSTANT, value=(255, 255, 255))
             for tile in tiles]
    rows = [np.hstack(tiles[i:i + STRIP_COLUMNS]) for i in range(0, len(tiles), STRIP_COLUMNS)]
    return np.vstack(rows)


def _point(xy) -> tuple[int, int]:
    return int(round(float(xy[0]))), int(round(float(xy[1])))


def _label(picture: np.ndarray, text: str, origin, colour) -> None:
    for thickness, ink in ((4, (255, 255, 255)), (1, colour)):
        cv2.putText(picture, text, _point(origin), cv2.FONT_HERSHEY_SIMPLEX, 0.55, ink, thickness + 1,
                    cv2.LINE_AA)


def _save(path: Path, rgb: np.ndarray) -> None:
    if not cv2.imwrite(str(path), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_PNG_COMPRESSION, 9]):
        raise OSError(f"could not write {path}")
    print(f"wrote {path} ({path.stat().st_size // 1024} KB)")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m actor.sim.pictures", description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, default=Path("deploy/figures"), help="output directory")
    parser.add_argument("--steps", type=int, default=150, help="length of the drive the strip is cut from")
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    config = EnvConfig()
    _save(args.out / "neighbourhood_map.png", map_picture(config))
    _save(args.out / "observation_strip.png", observation_strip(*drive_frames(config, args.steps)))


if __name__ == "__main__":
    main()
