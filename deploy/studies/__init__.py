"""Studies and their reports: the reports that rebuild from committed runs (the grid's among them), and the
comparisons between them. The grid runner itself is deploy/grid/."""
