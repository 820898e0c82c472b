"""Pictures of the simulator: the map with its start poses, and strips of camera frames.

    python -m actor.sim.pictures --out deploy/figures

writes

* ``neighbourhood_map.png``: roads, parked cars in red, trees, houses,
  training starts in blue and test starts in orange, numbered by
  ``start_index``, each with an arrow along its heading;
* ``camera_strips.png``: one drive of the privileged driver approaching and
  passing a parked car, a row per step (oldest at the top): what the front
  camera saw (the observation, 66 x 200) beside what the top-down camera
  would have seen at the same pose;
* ``traffic_strip.png``: the same pairs on a drive with moving traffic, at the
  steps where a traffic vehicle is in view.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import cv2
import numpy as np

from actor.sim import start_poses
from actor.sim.env import NeighbourhoodEnv
from actor.sim.neighbourhood import neighbourhood
from actor.sim.privileged import PrivilegedDriver
from actor.sim.world_image import world_image
from common.sim_config import EnvConfig

MAP_SCALE = 3.0  # px per metre of the map picture
START_COLOURS = {"train": (30, 110, 255), "test": (255, 140, 0)}  # RGB
STRIP_ROWS = 8
STRIP_ZOOM = 2
STRIP_START = ("train", 0)  # A1-B1 eastwards: two cars at the kerb, then one reaching into the lane
PASSING_M = 14.0  # a parked car this close ahead of the car counts as being approached or passed
TRAFFIC_VEHICLES = 12


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
            label(picture, str(index), centre + (-4, -10), colour)
    label(picture, "train starts", (12, 24), START_COLOURS["train"])
    label(picture, "test starts", (12, 48), START_COLOURS["test"])
    return picture


def drive_pairs(env_config: EnvConfig, steps: int, start: tuple[str, int] = STRIP_START,
                seed: int = 0) -> tuple[list[np.ndarray], list[np.ndarray], list[dict]]:
    """Front and top-down frames at every step of a privileged drive, and the env's state then."""
    env = NeighbourhoodEnv(env_config)
    front, _ = env.reset(seed=seed, options={"start_set": start[0], "start_index": start[1]})
    driver = PrivilegedDriver(env_config, seed=seed)
    driver.reset(env.pose)
    fronts, topdowns, states = [], [], []
    for _ in range(steps):
        fronts.append(front)
        topdowns.append(env.cameras("topdown").frame(*env.pose, env.traffic_rectangles()))
        states.append({"pose": env.pose, "traffic": env.traffic_rectangles()})
        front, _, terminated, truncated, _ = env.step(driver.act(env.pose, env.traffic_rectangles()))
        if terminated or truncated:
            break
    env.close()
    return fronts, topdowns, states


def _relative(pose: tuple[float, float, float], things: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """How far ahead of the pose and to its right the centres of ``things`` (rows x, y, ...) lie."""
    x, y, heading = pose
    dx, dy = things[:, 0] - x, things[:, 1] - y
    return dx * math.cos(heading) + dy * math.sin(heading), -dx * math.sin(heading) + dy * math.cos(heading)


def parked_car_ahead(pose: tuple[float, float, float], cars: np.ndarray) -> bool:
    """Whether a parked car's centre lies within PASSING_M ahead of the pose or just beside it."""
    along, across = _relative(pose, cars)
    return bool(np.any((along > -3.0) & (along < PASSING_M) & (np.abs(across) < 4.0)))


def traffic_ahead(pose: tuple[float, float, float], traffic: np.ndarray | None) -> bool:
    """Whether a traffic car lies 3 to 35 m ahead, within 45 degrees of the heading."""
    if traffic is None or not len(traffic):
        return False
    along, across = _relative(pose, traffic)
    return bool(np.any((along > 3.0) & (along < 35.0) & (np.abs(across) < along)))


def strip(fronts: list[np.ndarray], topdowns: list[np.ndarray], rows: list[int]) -> np.ndarray:
    """Rows of (front frame | top-down frame), enlarged, with a white rule between tiles."""
    def tile(frame: np.ndarray) -> np.ndarray:
        big = cv2.resize(frame, None, fx=STRIP_ZOOM, fy=STRIP_ZOOM, interpolation=cv2.INTER_NEAREST)
        return cv2.copyMakeBorder(big, 2, 2, 2, 2, cv2.BORDER_CONSTANT, value=(255, 255, 255))
    lines = [np.hstack([tile(fronts[i]), tile(topdowns[i])]) for i in rows]
    header = np.full((24, lines[0].shape[1], 3), 255, dtype=np.uint8)
    label(header, "front camera (the observation)", (8, 17), (0, 0, 0))
    label(header, "top-down camera, same pose", (lines[0].shape[1] // 2 + 8, 17), (0, 0, 0))
    return np.vstack([header, *lines])


def chosen_rows(wanted: list[bool]) -> list[int]:
    """STRIP_ROWS steps spread evenly over the first run of steps where ``wanted`` holds."""
    steps = np.flatnonzero(wanted)
    if len(steps) == 0:
        raise RuntimeError("the drive never showed what the strip is for")
    run_end = int(np.argmax(np.diff(steps, append=steps[-1] + 2) > 1))
    first, last = int(steps[0]), int(steps[run_end])
    return sorted({int(round(v)) for v in np.linspace(first, last, STRIP_ROWS)})


def camera_strips(env_config: EnvConfig, steps: int) -> np.ndarray:
    fronts, topdowns, states = drive_pairs(env_config, steps)
    cars = np.array([car.rectangle for car in neighbourhood().parked_cars])
    return strip(fronts, topdowns, chosen_rows([parked_car_ahead(s["pose"], cars) for s in states]))


def traffic_strip(env_config: EnvConfig, steps: int, seed: int = 1) -> np.ndarray:
    config = EnvConfig(**{**env_config.__dict__, "traffic_vehicles": TRAFFIC_VEHICLES})
    fronts, topdowns, states = drive_pairs(config, steps, start=("test", 3), seed=seed)
    return strip(fronts, topdowns, chosen_rows([traffic_ahead(s["pose"], s["traffic"]) for s in states]))


def _point(xy) -> tuple[int, int]:
    return int(round(float(xy[0]))), int(round(float(xy[1])))


def label(picture: np.ndarray, text: str, origin, colour) -> None:
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
    parser.add_argument("--steps", type=int, default=150, help="length of the drives the strips are cut from")
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    config = EnvConfig(start_jitter_m=0.0, start_jitter_deg=0.0)
    _save(args.out / "neighbourhood_map.png", map_picture(config))
    _save(args.out / "camera_strips.png", camera_strips(config, args.steps))
    _save(args.out / "traffic_strip.png", traffic_strip(config, 3 * args.steps))


if __name__ == "__main__":
    main()
