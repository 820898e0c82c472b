"""The grid on a Slurm cluster: its batch script and the helper that submits it (docs/slurm.md)."""
