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

from common.wire.state_rows import STATE_DTYPE


def state_row(hidden: torch.Tensor, cell: torch.Tensor) -> np.ndarray:
    """One step's row (2, lstm_units) from one simulator's h and c (any shape holding lstm_units values)."""
    return np.stack([hidden.detach().reshape(-1).cpu().numpy(),
                     cell.detach().reshape(-1).cpu().numpy()]).astype(STATE_DTYPE)


def lstm_state(rows: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Rows (B, 2, lstm_units) as the network's state (h, c), each (1, B, lstm_units) in float32."""
    rows = rows.float()
    return rows[None, :, 0].contiguous(), rows[None, :, 1].contiguous()
