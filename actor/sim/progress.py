"""Progress along the road network, and the stall rule that stops circling from counting as driving.

A collision-free rate is only a safety metric if the car had to drive to earn
it: a car that circles on a paved junction for 2,000 steps never touches
anything. So the simulator measures *new road covered*. The centre-lines
(streets and corner curves) are cut into cells of about ``CELL_M``; each step
the car's nearest centre-line point marks the cells it passed as visited, and
the step's progress is the length of the cells that nobody visited within the
last ``memory_steps`` (where the nearest piece changes, the straight gap
between the two nearest points instead, if the new cell is fresh, at most
the distance driven). Driving on
gains about a metre per metre; circling
gains only until its loop closes, then nothing; driving round a block gains
again once the block takes longer than the memory (the shortest block of the
map takes about 27 s at 10 m/s, the default memory is 20 s).

An episode has stalled when its progress over the last ``window_steps`` falls
below ``min_progress_m``; it is never judged before a full window has passed.
"""

from __future__ import annotations

from collections import deque

import numpy as np

from actor.sim.geometry import Segments

CELL_M = 1.0
NEVER = -(1 << 40)  # a step long before any episode starts


class ProgressMeter:
    def __init__(self, centre_lines: Segments, memory_steps: int, window_steps: int,
                 min_progress_m: float, step_m: float) -> None:
        """``step_m``: the distance the car drives in one step (it never drives farther)."""
        self.centre_lines = centre_lines
        lengths = np.sqrt(1.0 / centre_lines.inverse_lengths2)
        self.cells_per_segment = np.maximum(1, np.ceil(lengths / CELL_M)).astype(int)
        self.first_cell = np.concatenate([[0], np.cumsum(self.cells_per_segment)[:-1]])
        self.cell_length = np.repeat(lengths / self.cells_per_segment, self.cells_per_segment)
        self.memory_steps, self.window_steps, self.min_progress_m = memory_steps, window_steps, min_progress_m
        self.step_m = step_m
        self.last_visit = np.full(len(self.cell_length), NEVER, dtype=np.int64)
        self.recent: deque[float] = deque(maxlen=window_steps)
        self.step = 0
        self.segment, self.cell, self.t = -1, -1, 0.0
        self.total_m = 0.0

    def reset(self, segment: int, t: float) -> None:
        """A new episode starting at ``t`` (0 to 1) along centre-line segment ``segment``."""
        self.last_visit[:] = NEVER
        self.recent.clear()
        self.step, self.total_m = 0, 0.0
        self.segment, self.cell, self.t = segment, self._cell(segment, t), t
        self.last_visit[self.cell] = 0

    def update(self, segment: int, t: float) -> float:
        """The progress in metres of one more step that ends at ``t`` along ``segment``."""
        self.step += 1
        cell = self._cell(segment, t)
        if segment == self.segment:
            progress = self._pass(self.cell, cell)
        else:
            # From one centre-line piece to the next (a street into a corner curve, say): the
            # pieces overlap near junctions, so cells are no ruler here; the step's progress is
            # the straight gap between the two nearest points, if it reached fresh road, and
            # never more than the car drove (nearest points of two pieces can lie far apart).
            fresh = self._pass(cell, cell) > 0
            progress = min(self._gap(self.segment, self.t, segment, t), self.step_m) if fresh else 0.0
        self.segment, self.cell, self.t = segment, cell, t
        self.recent.append(progress)
        self.total_m += progress
        return progress

    def _pass(self, first_cell: int, last_cell: int) -> float:
        """Marks the cells between two of one piece as visited now; their fresh length."""
        passed = slice(min(first_cell, last_cell), max(first_cell, last_cell) + 1)
        fresh = self.last_visit[passed] < self.step - self.memory_steps
        self.last_visit[passed] = self.step
        return float(self.cell_length[passed][fresh].sum())

    def _gap(self, old: int, old_t: float, new: int, new_t: float) -> float:
        lines = self.centre_lines
        old_point = lines.starts[old] + old_t * lines.deltas[old]
        new_point = lines.starts[new] + new_t * lines.deltas[new]
        return float(np.hypot(*(new_point - old_point)))

    @property
    def stalled(self) -> bool:
        return len(self.recent) == self.window_steps and sum(self.recent) < self.min_progress_m

    def _cell(self, segment: int, t: float) -> int:
        count = self.cells_per_segment[segment]
        return int(self.first_cell[segment] + min(int(t * count), count - 1))
