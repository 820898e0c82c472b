"""Q-values for several simulators stepped in lockstep: one batched forward pass, one LSTM state each.

The training actor (actor/runner.py) and the evaluation workers
(actor/evaluation/episodes.py) both drive a set of simulators, "slots", with
one network. At every step the slots that are running go through the network
together; each slot's recurrent state is gathered for the pass and written
back after it, so a slot's state depends only on its own frames since it was
last reset. A batch of one is exactly the single-env forward pass.
"""

from __future__ import annotations

import numpy as np
import torch

from common.network import D3RQN


class BatchedQ:
    def __init__(self, network: D3RQN, n_slots: int) -> None:
        self.network = network.eval()
        self.hidden, self.cell = network.initial_state(n_slots)

    @torch.no_grad()
    def reset(self, slot: int) -> None:
        """The slot starts an episode: its LSTM state is zeroed, the others' are kept."""
        self.hidden[:, slot] = 0.0
        self.cell[:, slot] = 0.0

    @torch.inference_mode()
    def q_values(self, slots: list[int], observations: list[np.ndarray]) -> torch.Tensor:
        """(len(slots), n_actions): each slot's Q-values after its observation; advances those slots' states."""
        index = torch.tensor(slots)
        frames = torch.from_numpy(np.stack(observations)).unsqueeze(1)  # (batch, time = 1, H, W, C)
        q_values, (hidden, cell) = self.network(frames, (self.hidden[:, index], self.cell[:, index]))
        self.hidden[:, index] = hidden
        self.cell[:, index] = cell
        return q_values[:, 0]
