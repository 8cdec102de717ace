"""Experiment files (TOML) -> validated experiments, one parser per world.

``load_experiment`` reads a file and hands it to the parser of its world: a file with a
``[servo]`` section is a servo experiment (paper 003), one with ``[airborne]`` an
airborne-radar experiment (paper 001), any other an open-loop tracking experiment.
Everything is checked before anything is compiled; a bad field raises ``ConfigError``
whose message is one line: file, field, value, what is allowed.

The parsers build the experiments of ``tracklab.experiments`` from the worlds, filters,
scenarios and sensors; nothing below imports this package.
"""

from __future__ import annotations

from pathlib import Path

import jax

from tracklab.config.airborne import parse_airborne
from tracklab.config.fields import MAX_RUN_STEPS, MAX_RUNS, MAX_STEPS, read_toml
from tracklab.config.servo import parse_servo
from tracklab.config.tracking import parse_tracking

__all__ = ["MAX_RUNS", "MAX_RUN_STEPS", "MAX_STEPS", "load_experiment", "parse_experiment"]


def parse_experiment(path, raw: dict):
    """Validate an experiment file's contents ``raw`` (its TOML as a dictionary) read from ``path``."""
    path = Path(path)
    with jax.enable_x64(True):  # a number the parsers compute is float64 whatever JAX's global mode
        if isinstance(raw, dict) and "servo" in raw:
            return parse_servo(path, raw)
        if isinstance(raw, dict) and "airborne" in raw:
            return parse_airborne(path, raw)
        return parse_tracking(path, raw)


def load_experiment(path):
    """Read and validate an experiment file (any world: open loop, airborne, servo)."""
    path = Path(path)
    return parse_experiment(path, read_toml(path))
