"""Running the system: the launcher, the reliability labs, the grid runner and its reports, the tools and the
benchmarks, each in a folder of its own; the main job and the reference loop at the top."""
