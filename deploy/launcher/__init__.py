"""The launcher: the stack that starts, restarts and watches the processes of one run on one machine, its
console line, the claim on the run folder and the disk watch."""
