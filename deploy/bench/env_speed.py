"""Simulator steps per second on one core, observation included: three renderers side by side.

Rows, all on the same neighbourhood road (same RoadNetwork, obstacles and
highway-env motion model), measured one after the other in one run:

* front camera (the default): ``NeighbourhoodEnv.step`` with the perspective
  camera, uniformly random actions, resets included (random driving ends an
  episode every few dozen steps, as in the paper's 999 episodes of random play);
* top-down camera: the same, with the heading-up map crop;
* highway-env GrayscaleObservation: the same env and dynamics, but the
  observation is highway-env's built-in pygame renderer (200 x 66, one frame);
* the front camera again with the privileged driver (long episodes through
  junctions; the driver's own time is included);
* highway-env Road.step only: highway-env's own simulation step of the ego car
  on this road (``Vehicle.step`` with its closest-lane search, then
  ``Road.step``'s collision checks against every object), without any
  observation: the part our env replaces with vectorised queries.

Then the ratios of the cameras to highway-env's renderer, and the per-call
cost of each part of a step. The machine may be shared: figures are what was
measured, on the CPU this process is pinned to.

    .venv/bin/python deploy/bench/env_speed.py [--steps 20000] [--highway-steps 1000]
"""

from __future__ import annotations

import argparse
import os
import time

import cv2
import numpy as np

from actor.sim.env import NeighbourhoodEnv
from actor.sim.privileged import PrivilegedDriver
from common.cpu_capability import describe_cpu
from common.sim_config import EnvConfig

GRAYSCALE = {"type": "GrayscaleObservation", "observation_shape": (200, 66), "stack_size": 1,
             "weights": [0.2989, 0.5870, 0.1140], "scaling": 200 / 24.0}  # same width as our camera


def one_core() -> int:
    """Pins this process to one CPU and every thread pool to one thread."""
    cpu = min(os.sched_getaffinity(0))
    os.sched_setaffinity(0, {cpu})
    cv2.setNumThreads(1)
    try:
        import torch
        torch.set_num_threads(1)
    except ImportError:
        pass
    return cpu


def random_actions_speed(env: NeighbourhoodEnv, steps: int, seed: int = 0) -> float:
    rng = np.random.default_rng(seed)
    actions = rng.integers(env.action_space.n, size=steps)
    env.reset(seed=seed)
    start = time.perf_counter()
    for action in actions:
        _, _, terminated, truncated, _ = env.step(int(action))
        if terminated or truncated:
            env.reset()
    return steps / (time.perf_counter() - start)


def privileged_speed(env: NeighbourhoodEnv, steps: int) -> float:
    driver = PrivilegedDriver(env.env_config, seed=0)
    done, start = 0, time.perf_counter()
    while done < steps:
        env.reset(options={"start_set": "train", "start_index": done % 10})
        driver.reset(env.pose)
        truncated = terminated = False
        while not (terminated or truncated) and done < steps:
            _, _, terminated, truncated, _ = env.step(driver.act(env.pose, env.traffic_rectangles()))
            done += 1
    return steps / (time.perf_counter() - start)


def highway_road_step_speed(env: NeighbourhoodEnv, steps: int) -> float:
    """highway-env's own stepping of the ego car on our road (no observation)."""
    env.reset(options={"start_set": "train", "start_index": 0})
    env.vehicle.action = {"steering": 0.0, "acceleration": 0.0}
    dt = 1.0 / env.env_config.policy_frequency
    start = time.perf_counter()
    for _ in range(steps):
        env.road.act()
        env.road.step(dt)
    return steps / (time.perf_counter() - start)


def part_costs_us(env: NeighbourhoodEnv, repeats: int = 5000) -> dict[str, float]:
    """Microseconds per call of each part of one step, at a pose next to a parked car."""
    env.reset(options={"start_set": "train", "start_index": 0})
    x, y, heading = env.pose
    hood, front, topdown = env.hood, env.cameras("front"), env.cameras("topdown")
    locator = env.vehicle.locator

    def timed(function) -> float:
        start = time.perf_counter()
        for _ in range(repeats):
            function()
        return (time.perf_counter() - start) / repeats * 1e6

    return {
        "front camera frame": timed(lambda: front.frame(x, y, heading)),
        "top-down camera frame": timed(lambda: topdown.frame(x, y, heading)),
        "highway-env Vehicle.step (one frame)": timed(lambda: env.vehicle.step(0.0)),
        "lane lookup (LaneLocator)": timed(lambda: locator.locate(x, y, heading)),
        "nearest centre-line": timed(lambda: hood.centre_lines.nearest(x, y)),
        "collision test, nothing near": timed(lambda: hood.obstacles.hits(x, y, heading, 4.5, 1.8)),
        "collision test, beside a parked car": timed(lambda: hood.obstacles.hits(21.0, 0.0, 0.0, 4.5, 1.8)),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--steps", type=int, default=20_000, help="steps for our env")
    parser.add_argument("--highway-steps", type=int, default=1_000, help="steps for highway-env's renderer")
    args = parser.parse_args()
    print(f"CPU: {describe_cpu()}", flush=True)
    cpu = one_core()
    front = NeighbourhoodEnv(EnvConfig(camera="front"))
    topdown = NeighbourhoodEnv(EnvConfig(camera="topdown"))
    config = front.env_config
    grayscale = NeighbourhoodEnv(config, observation=GRAYSCALE)
    print(f"pinned to CPU {cpu}; cv2 threads {cv2.getNumThreads()}; speed {config.speed} m/s, "
          f"{config.policy_frequency} Hz decisions, {config.simulation_frequency} Hz simulation")
    rows = {
        "front": ("front camera, random actions, resets included", random_actions_speed(front, args.steps)),
        "topdown": ("top-down camera, random actions, resets included", random_actions_speed(topdown, args.steps)),
        "highway": ("highway-env GrayscaleObservation (200x66), random actions",
                    random_actions_speed(grayscale, args.highway_steps)),
        "privileged": ("front camera, privileged driver", privileged_speed(front, args.steps)),
        "road_step": ("highway-env Road.step only, no observation",
                      highway_road_step_speed(NeighbourhoodEnv(config), args.highway_steps)),
    }
    for name, rate in rows.values():
        print(f"{name:<62} {rate:10,.0f} steps/s")
    highway = rows["highway"][1]
    print(f"front camera / highway-env GrayscaleObservation: {rows['front'][1] / highway:.1f}x")
    print(f"top-down camera / highway-env GrayscaleObservation: {rows['topdown'][1] / highway:.1f}x")
    print(f"front camera / top-down camera: {rows['front'][1] / rows['topdown'][1]:.2f}x")
    for name, cost in part_costs_us(front).items():
        print(f"  {name:<40} {cost:8.1f} us")


if __name__ == "__main__":
    main()
