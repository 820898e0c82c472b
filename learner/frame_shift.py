"""Random-shift augmentation of the frames the learner trains on (learner.shift_pad, beyond the paper).

DrQ (Kostrikov et al. 2020, "Image Augmentation Is All You Need"; its DQN form DrQ(epsilon) in Dopamine's
Atari-100k configurations) pads each frame by 4 pixels, repeating the edge, and crops it back to its size at
a random offset. Here the offset is drawn once per trace, not per frame, so that the LSTM reads a sequence
whose camera does not jump from step to step; the online and target passes read the same shifted frames.
"""

from __future__ import annotations

import torch


def draw_offsets(generator: torch.Generator, traces: int, pad: int) -> torch.Tensor:
    """One (rows, columns) offset per trace, each uniform in [-pad, pad]: int64 (traces, 2), on the CPU."""
    return torch.randint(-pad, pad + 1, (traces, 2), generator=generator)


def shift_frames(frames: torch.Tensor, offsets: torch.Tensor) -> torch.Tensor:
    """Frames (B, T, H, W, C) with trace b moved by offsets[b] = (dy, dx):
    out[b, t, i, j] = frames[b, t, clamp(i + dy), clamp(j + dx)].

    That is the edge-replicating pad by p >= |dy|, |dx| and the crop at (p + dy, p + dx), done as one index
    per axis (the clamp repeats the edge); a loop over the traces, each of whose steps shares its offset.
    """
    _, _, height, width, _ = frames.shape
    rows = torch.arange(height, device=frames.device)
    columns = torch.arange(width, device=frames.device)
    shifted = torch.empty_like(frames)
    for trace, (dy, dx) in enumerate(offsets.tolist()):
        shifted[trace] = (frames[trace].index_select(1, (rows + dy).clamp_(0, height - 1))
                          .index_select(2, (columns + dx).clamp_(0, width - 1)))
    return shifted
