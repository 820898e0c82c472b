"""Watching a policy drive (deploy/tools/animate_policy.py): the video holds a frame every --stride steps and the
last, of the stated size, and the episode is the evaluation's own for that start and trial."""

import cv2
import pytest
import torch

from actor.evaluation.episodes import EpisodeJob, evaluation_env_config, make_policies, run_lockstep, trial_seed
from actor.sim import make_env
from common.checkpoint import KeptPolicy
from common.config_values import load_config, to_dict
from common.network import D3RQN
from deploy.tools import animate_policy

FRAME_SIZE = (900, 300)  # width, height: the 198 x 600 camera frame and its caption beside the 300 x 300 view


@pytest.fixture
def policy_file(tmp_path):
    """An untrained tiny network's kept policy."""
    config = load_config("smoke", overrides={"network.lstm_units": 16})
    torch.manual_seed(0)
    path = tmp_path / "policy.pt"
    KeptPolicy(updates=5, env_steps=200, wall_s=1.0, cpu="Test CPU", config=to_dict(config),
               online=D3RQN(config.network).state_dict()).save(path)
    return path


def video_frames(path) -> list:
    capture = cv2.VideoCapture(str(path))
    frames = []
    while True:
        ok, frame = capture.read()
        if not ok:
            break
        frames.append(frame)
    capture.release()
    return frames


def animate(policy_file, out, *flags):
    args = animate_policy.parse_flags(animate_policy.build_parser(),
                                      ["--checkpoint", str(policy_file), "--out", str(out), *flags])
    return animate_policy._main(args)


def test_a_drive_cut_at_max_steps_has_a_frame_every_stride_and_the_last(policy_file, tmp_path, capsys):
    out = tmp_path / "videos" / "drive.mp4"
    drive = animate(policy_file, out, "--start-set", "test", "--start", "0", "--max-steps", "5", "--stride", "2")
    assert (drive.steps, drive.end) == (5, "cut")
    assert (drive.frames, drive.frame_size) == (4, FRAME_SIZE)  # steps 0, 2, 4 and the last, 5
    frames = video_frames(out)
    assert len(frames) == 4 and all(frame.shape == (FRAME_SIZE[1], FRAME_SIZE[0], 3) for frame in frames)
    assert f"wrote {out}: 4 frames of 900 x 300" in capsys.readouterr().out


def test_the_drive_is_the_evaluations_episode_of_that_start_and_trial(policy_file, tmp_path):
    cap = ["--evaluation.max_steps", "40"]
    drive = animate(policy_file, tmp_path / "drive.mp4", "--start-set", "train", "--start", "3", "--trial", "1",
                    "--stride", "3", *cap)
    saved = KeptPolicy.load(policy_file)
    config = load_config("smoke", overrides={"network.lstm_units": 16, "evaluation.max_steps": 40})
    job = EpisodeJob("greedy", "train", 3, 1, trial_seed(config.evaluation.seed, "train", 3, 1))
    episodes = []
    env = make_env(evaluation_env_config(config))
    run_lockstep([job], [env], make_policies(config, saved.weights(), 1), 40, config.evaluation.reward_bins,
                 episodes.append)
    env.close()
    assert (drive.steps, drive.end) == (episodes[0].length, episodes[0].end)
    expected = len(range(0, drive.steps + 1, 3)) + (drive.steps % 3 != 0)  # every third step, and the last
    assert drive.frames == expected == len(video_frames(tmp_path / "drive.mp4"))


@pytest.mark.parametrize("flags, message", [
    (["--out", "drive.gif"], "the video is an .mp4, not 'drive.gif'"),
    (["--start", "10"], "the test set has starts 0 to 9"),
    (["--stride", "0"], "--stride and --max-steps must be >= 1"),
])
def test_a_wrong_request_is_one_line_before_any_driving(policy_file, tmp_path, capsys, flags, message):
    with pytest.raises(SystemExit) as exit_info:
        animate_policy.main(["--checkpoint", str(policy_file), "--out", str(tmp_path / "drive.mp4"), *flags])
    assert exit_info.value.code == 1
    error = capsys.readouterr().err
    assert error.startswith("animate_policy: error:") and message in error
