"""The LSTM state an actor stores with each step: learner.stored_state, beyond the paper (R2D2's stored state).

Before each step an actor records the state its network holds as it takes in that step's observation: h
and c, in float16, as one row (2, lstm_units) of the episode's array (steps, 2, lstm_units), 4 x lstm_units
bytes a step (2,048 at the paper's 512 units, beside a frame's ~3 KB of JPEG). The replay keeps the array
with the episode and hands each trace the row of its first step; the learner starts the trace from it.
float16 holds h (in (-1, 1)) to 3 decimal places and c, which grows by less than 1 a step, to its range
(|c| < 2,000 in a 2,000-step episode, far below float16's 65,504).
"""

from __future__ import annotations

import numpy as np
import torch

STATE_DTYPE = np.float16


def stored_units(config) -> int:
    """The units of the state rows a run's episodes carry (a Config of common/config.py): 0 when it stores none."""
    return config.network.lstm_units if config.learner.stored_state else 0


def bytes_per_step(lstm_units: int) -> int:
    """What one stored step's state takes: h and c, lstm_units values each, 2 bytes a value."""
    return 2 * lstm_units * np.dtype(STATE_DTYPE).itemsize


def no_states() -> np.ndarray:
    """The array of an episode recorded without states."""
    return np.zeros((0, 2, 0), dtype=STATE_DTYPE)


def state_row(hidden: torch.Tensor, cell: torch.Tensor) -> np.ndarray:
    """One step's row (2, lstm_units) from one simulator's h and c (any shape holding lstm_units values)."""
    return np.stack([hidden.detach().reshape(-1).cpu().numpy(),
                     cell.detach().reshape(-1).cpu().numpy()]).astype(STATE_DTYPE)


def lstm_state(rows: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Rows (B, 2, lstm_units) as the network's state (h, c), each (1, B, lstm_units) in float32."""
    rows = rows.float()
    return rows[None, :, 0].contiguous(), rows[None, :, 1].contiguous()
