"""Studies over experiments: tuning by gradient through the Monte-Carlo runs (``tune``), sweeps
over any number of a file (``sweep``), and the studies' files — a tuning's tuned file and report,
the ``[[study]]`` tables ``tracklab reproduce`` rebuilds (``files``).
"""
