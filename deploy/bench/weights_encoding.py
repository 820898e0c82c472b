"""How far compact weights (learner.weights_encoding) and the bfloat16 actor pass (actor.inference) move the
greedy policy, on real frames.

Frames come from the simulator: drives of the privileged driver from the training starts, with a
random action instead at a quarter of the steps (so the car also drifts), each cut at
--drive-steps. Every network runs over each drive from a zero state, as an actor steps it, once
with its float32 weights and once with the same weights sent in each compact encoding (encoded,
decoded and widened as an actor loads them), and once with float32 weights through the actor's bfloat16
pass (actor/batched_q.py). Reported per network and variant: the share of steps
whose greedy action changes, the largest |Q difference| and, for scale, the largest |Q|.
Networks: seeded random inits (--seeds) and the online network of each --checkpoint.

    .venv/bin/python deploy/bench/weights_encoding.py [--frames 4000] [--checkpoint runs/r/checkpoints/latest.pt]
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from actor.batched_q import BatchedQ
from actor.sim import make_env
from actor.sim.privileged import PrivilegedDriver
from common.checkpoint import Checkpoint
from common.config import Config, NetworkConfig
from common.sim_config import EnvConfig
from common.config_values import from_dict
from common.cpu_capability import bfloat16_problem, describe_cpu
from common.network import D3RQN, load_numpy_weights, weights_to_numpy
from common.wire.envelope import decode, encode
from common.wire.messages import Weights
from common.wire.weights_encoding import WEIGHTS_ENCODINGS

BFLOAT16_PASS = "bf16 pass"  # float32 weights, the actor's bfloat16 forward pass
VARIANTS = tuple(encoding for encoding in WEIGHTS_ENCODINGS if encoding != "float32") + (BFLOAT16_PASS,)
RANDOM_ACTION_SHARE = 0.25


@dataclass(frozen=True)
class Difference:
    """What a compact encoding changes in one network's outputs over the same frames."""

    frames: int
    greedy_changed: float  # share of steps whose greedy action differs from float32's
    max_abs_q_difference: float
    max_abs_q: float  # float32's, for scale


def drives(env_config: EnvConfig, frames: int, drive_steps: int, seed: int = 0) -> list[np.ndarray]:
    """Observations (uint8 [steps, H, W, C]) of drives adding up to `frames` frames."""
    env = make_env(env_config, seed=seed).unwrapped
    rng = np.random.default_rng(seed)
    found: list[np.ndarray] = []
    total = 0
    while total < frames:
        observation, _ = env.reset(options={"start_set": "train", "start_index": len(found) % 10})
        driver = PrivilegedDriver(env_config, seed=seed + len(found))
        driver.reset(env.pose)
        drive = [observation]
        while len(drive) < min(drive_steps, frames - total):
            action = driver.act(env.pose, env.traffic_rectangles())
            if rng.random() < RANDOM_ACTION_SHARE:
                action = int(rng.integers(env.action_space.n))
            observation, _, terminated, truncated, _ = env.step(action)
            if terminated or truncated:
                break
            drive.append(observation)
        found.append(np.stack(drive))
        total += len(drive)
    env.close()
    return found


def as_sent(network_config: NetworkConfig, tensors: dict[str, np.ndarray], encoding: str) -> D3RQN:
    """The network an actor holds after receiving these float32 tensors in the given encoding."""
    message = decode(encode(Weights.from_float32(1, tensors, encoding)), Weights)
    network = D3RQN(network_config).eval()
    load_numpy_weights(network, message.to_float32())
    return network


@torch.inference_mode()
def q_values(network: D3RQN, observations: list[np.ndarray]) -> np.ndarray:
    """Q-values [frames, n_actions] of every drive, each from a zero state."""
    return np.concatenate([network(torch.from_numpy(drive)[None])[0][0].numpy() for drive in observations])


def stepped_q_values(network: D3RQN, observations: list[np.ndarray], precision: str) -> np.ndarray:
    """The same, one frame at a time through the actor's pass in `precision`."""
    batched = BatchedQ(network, 1, precision)
    rows = []
    for drive in observations:
        batched.reset(0)
        rows += [batched.q_values([0], [frame])[0].numpy() for frame in drive]
    return np.stack(rows)


def variant_q_values(network_config: NetworkConfig, tensors: dict[str, np.ndarray], variant: str,
                     observations: list[np.ndarray]) -> np.ndarray:
    if variant == BFLOAT16_PASS:
        return stepped_q_values(as_sent(network_config, tensors, "float32"), observations, "bfloat16")
    return q_values(as_sent(network_config, tensors, variant), observations)


def compare(network_config: NetworkConfig, tensors: dict[str, np.ndarray], variant: str,
            observations: list[np.ndarray]) -> Difference:
    q_reference = q_values(as_sent(network_config, tensors, "float32"), observations)
    q_compact = variant_q_values(network_config, tensors, variant, observations)
    changed = q_reference.argmax(axis=1) != q_compact.argmax(axis=1)
    return Difference(len(q_reference), float(changed.mean()), float(np.abs(q_reference - q_compact).max()),
                      float(np.abs(q_reference).max()))


def networks(config: Config, seeds: int, checkpoints: list[Path]) -> dict[str, dict[str, np.ndarray]]:
    """Float32 tensors by name of what they are: random inits, then each checkpoint's online network."""
    found = {}
    for seed in range(seeds):
        torch.manual_seed(seed)
        found[f"random init, seed {seed}"] = weights_to_numpy(D3RQN(config.network))
    for path in checkpoints:
        checkpoint = Checkpoint.load(path)
        if from_dict(checkpoint.config).network != config.network:
            raise SystemExit(f"{path}: a network of other sizes than the default")
        found[f"{path} ({checkpoint.updates} updates)"] = checkpoint.policy_weights()
    return found


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=4000)
    parser.add_argument("--drive-steps", type=int, default=200)
    parser.add_argument("--seeds", type=int, default=3, help="random inits to measure")
    parser.add_argument("--checkpoint", type=Path, action="append", default=[])
    args = parser.parse_args()
    print(f"CPU: {describe_cpu()}", flush=True)
    torch.set_num_threads(1)
    config = Config()
    observations = drives(config.env, args.frames, args.drive_steps)
    print(f"{sum(map(len, observations))} frames in {len(observations)} drives (privileged driver, "
          f"{RANDOM_ACTION_SHARE:.0%} random actions)")
    print(f"{'network':58s} {'variant':9s} {'greedy changed':>14s} {'max |dQ|':>10s} {'max |Q|':>9s}")
    variants = VARIANTS
    if bfloat16_problem() is not None:
        variants = [variant for variant in VARIANTS if variant != BFLOAT16_PASS]
        print(f"skipping the {BFLOAT16_PASS} variant: {bfloat16_problem()}")
    for name, tensors in networks(config, args.seeds, args.checkpoint).items():
        for variant in variants:
            difference = compare(config.network, tensors, variant, observations)
            print(f"{name[-58:]:58s} {variant:9s} {difference.greedy_changed:14.2%} "
                  f"{difference.max_abs_q_difference:10.2e} {difference.max_abs_q:9.3g}")


if __name__ == "__main__":
    main()
