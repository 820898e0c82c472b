"""The LSTM state rows that travel with episodes and trace batches (learner.stored_state, common/stored_state.py
says what they hold): their dtype and size, the empty array of an episode recorded without them, and how many
units a run's rows have. Numpy only: the wire carries them.
"""

from __future__ import annotations

import numpy as np

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
