"""The grid runner: the cells of the grid (grid_cells.py), the job of one cell (grid_job.py), the runner
that schedules them (experiments.py) and the child processes it starts (child_process.py)."""
