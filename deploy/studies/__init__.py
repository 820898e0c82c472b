"""Studies and their reports: the grid runner (experiments.py, a cell's job grid_job.py, its cells
grid_cells.py), the reports that rebuild from committed runs, and the comparisons between them."""
