"""Checked values of experiment-file fields that the configuration and the filter kinds share.

A leaf module: it imports nothing of tracklab but the error users see.
"""

from __future__ import annotations

from tracklab.errors import ConfigError

MAX_MAGNITUDE = 1e15  # largest accepted magnitude: squares stay finite in float64


def sigma_list(f, field_name, s, dim, required=True):
    """A number, or a list of one per axis (component), each in (0, MAX_MAGNITUDE] -> a tuple of ``dim`` floats."""
    if s is None:
        if required:
            raise ConfigError(f, field_name, None, "is required (a number or a list of one per axis)")
        return None
    vals = s if isinstance(s, list) else [s] * dim
    if len(vals) != dim:
        raise ConfigError(f, field_name, s, f"must have {dim} values (one per axis) or be a single number")
    for v in vals:
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0 < v <= MAX_MAGNITUDE:
            raise ConfigError(f, field_name, s, f"each value must be a number in (0, {MAX_MAGNITUDE:g}]")
    return tuple(float(v) for v in vals)
