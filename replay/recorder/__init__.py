"""The flight recorder and its log tools: a run's Zenoh messages in one MCAP file.

``recorder`` writes the file while the system runs, ``reader`` and ``recover`` read
it back (also after a crash), ``play`` puts it back on Zenoh, ``export`` and ``plot``
turn it into CSV tables, a Foxglove viewing file and training curves; ``cli`` is
the ``d3rqn-log`` command.
"""
