"""The paper's evaluation protocol for one policy, in the modules named for each part.

episodes (which episodes, the policies, lockstep stepping inside a worker),
workers (the worker processes), status (the status line), protocol (policies
x start sets -> episodes and table rows), sources (the weights: a checkpoint or
the live learner), curve (the greedy learning curve of the policies a run kept).
The tables' figures and files (stats, intervals, tables) are in common/analysis/,
which the comparison across runs (deploy/studies/comparison.py) shares. The command
line is actor/evaluation/command.py.
"""


class EvaluationError(RuntimeError):
    """The evaluation cannot run: no weights, unusable settings, or a worker failed."""
