"""Reading the studies an experiment file asks ``tracklab reproduce`` to rebuild: tuning and sweeps.

An experiment file may hold ``[[study]]`` tables; each is checked with the rest
of the file, before anything compiles::

    [[study]]                       # results/tuning/stf_tuned.toml, stf_tune.log, stf_tuned/
    kind = "tune"
    params = ["rho", "b"]
    filters = ["STF"]               # default: every filter with the parameters
    loss = "pred_mse"               # mse_pos | pred_mse | nll
    steps = 150
    lr = 0.05
    runs_per_step = 32
    out = "tuning/stf"

    [[study]]                       # results/mismatch/lidar_crossing/
    kind = "sweep"
    grid = ["q=0.01:100:5", "r=0.04:25:5"]
    runs = 1000
    out = "mismatch/lidar_crossing"

A tune study writes the tuned experiment file ``<out>_tuned.toml``, the progress
lines ``<out>_tune.log`` and the results of running the tuned file, ``<out>_tuned/``;
a sweep study writes the sweep folder ``<out>/`` (all under the results folder).
These are exactly what ``tracklab tune … --out <out>_tuned.toml`` then ``tracklab
run <out>_tuned.toml``, and ``tracklab sweep … --out <out>`` give.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from tracklab.config.fields import MAX_RUNS, Section
from tracklab.config.paths import parse_grid
from tracklab.errors import ConfigError
from tracklab.worlds.tracking.errors import LOSSES
from tracklab.worlds.tracking.experiment import declared_of

OUT_RE = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]*(/[A-Za-z0-9_][A-Za-z0-9_.-]*)*")


@dataclass(frozen=True)
class TuneStudy:
    params: tuple[str, ...]
    filters: tuple[str, ...] | None
    loss: str
    steps: int
    lr: float
    runs_per_step: int
    out: str
    kind: str = "tune"


@dataclass(frozen=True)
class SweepStudy:
    grid: tuple[str, ...]
    runs: int | None
    out: str
    kind: str = "sweep"


def parse_studies(f, tables, exp_filters) -> list:
    """Validate the ``[[study]]`` tables of an open-loop file whose filters are ``exp_filters``."""
    if tables is None:
        return []
    if not isinstance(tables, list) or not all(isinstance(t, dict) for t in tables):
        raise ConfigError(f, "[[study]]", tables, "must be one or more [[study]] tables")
    labels = {fc.label: fc for fc in exp_filters}
    studies, outs = [], set()
    for i, table in enumerate(tables, start=1):
        st = Section(f, f"study[{i}]", table)
        kind = st.string("kind", required=True, choices=("tune", "sweep"))
        out = st.string("out", required=True)
        if not OUT_RE.fullmatch(out) or ".." in out.split("/") or len(out) > 200:
            raise ConfigError(f, f"study[{i}].out", out, "must be a relative folder under results/ (letters, digits, _ . - and /)")
        if out in outs:
            raise ConfigError(f, f"study[{i}].out", out, "must be unique among the studies")
        outs.add(out)
        if kind == "tune":
            params = st.get("params")
            tunable = list(dict.fromkeys(n for fc in exp_filters for n, p in declared_of(fc).items() if p.tune))
            if not isinstance(params, list) or not params or any(p not in tunable for p in params):
                raise ConfigError(f, f"study[{i}].params", params, f"must be a list of parameters among {', '.join(tunable)}")
            chosen = st.get("filters")
            if chosen is not None and (not isinstance(chosen, list) or not chosen or any(c not in labels for c in chosen)):
                raise ConfigError(f, f"study[{i}].filters", chosen, f"must be a list of filter labels from: {', '.join(labels)}")
            pool = [labels[c] for c in chosen] if chosen else list(labels.values())
            if not any(p in declared_of(fc) and declared_of(fc)[p].tune for fc in pool for p in params):
                raise ConfigError(f, f"study[{i}].params", params, "no selected filter has any of these parameters")
            loss = st.string("loss", "mse_pos", choices=tuple(LOSSES))
            lr = st.number("lr", 0.05, positive=True)
            study = TuneStudy(tuple(params), tuple(chosen) if chosen else None, loss,
                              st.integer("steps", 200, lo=1, hi=100_000), lr,
                              st.integer("runs_per_step", 256, lo=1, hi=1_000_000), out)
        else:
            grid = st.get("grid")
            if not isinstance(grid, list) or not grid or any(not isinstance(g, str) for g in grid):
                raise ConfigError(f, f"study[{i}].grid", grid, "must be a list of NAME=LO:HI:N strings")
            axes = []
            for g in grid:
                try:
                    axes.append(parse_grid(g))
                except ValueError as e:
                    raise ConfigError(f, f"study[{i}].grid", g, str(e)) from None
            names = [a.name for a in axes]
            if len(set(names)) != len(names):
                raise ConfigError(f, f"study[{i}].grid", grid, "each parameter may appear once")
            # scale factors need a filter with the parameter; a PATH is checked against the file by the sweep
            missing = next((a.name for a in axes if a.path is None
                            and not any(a.name in declared_of(fc) and declared_of(fc)[a.name].sweep
                                        for fc in exp_filters)), None)
            if missing:
                raise ConfigError(f, f"study[{i}].grid", grid, f"no filter of this experiment has the parameter {missing!r}")
            study = SweepStudy(tuple(grid), st.integer("runs", None, lo=1, hi=MAX_RUNS), out)
        st.check_unknown()
        studies.append(study)
    return studies
