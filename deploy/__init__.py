"""Running the system: the local stack, the experiment grid and its cross-run comparison, benchmarks."""
