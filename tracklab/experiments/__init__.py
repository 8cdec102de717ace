"""Validated experiments, one module per world: what a file describes, as the world's
structure and numbers, with its Monte-Carlo run, statistics and results folder.

``tracking`` (open loop), ``airborne`` (paper 001's closed loop), ``servo`` (paper 003).
They use the worlds, the runner and the report; ``tracklab.config`` builds them from files.
"""
