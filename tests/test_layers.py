"""Imports go downward only: each part of the package uses the parts below it, never one above.

Bottom to top: the building blocks (filters, models, sensors, scenarios, the runner and its
statistics, …); the report (results folders, tables and figures from statistics documents); the
worlds and their experiments; the experiment-file parsers (config); the studies (tune, sweep and
their files); the command line; the public API. A circle, or a world importing its
parser, fails here with the module and the import that goes up.

Apart from the layers, the top: ``import tracklab`` and the command's module (``tracklab.cli``)
import nothing heavy (no JAX, no NumPy, not the engine), so that the command installs its SIGINT
handler (``tracklab.interrupts``, which imports only the standard library) before anything else;
the public names are served on first use, as if imported.
"""

import ast
import subprocess
import sys
from pathlib import Path

import pytest

import tracklab

LAYERS = [
    {"errors", "checks", "interrupts", "runtime", "processes", "progress", "pytree", "parameters", "linalg", "batching", "random", "toml_fields", "memory", "output", "models", "sensors",
     "scenarios", "intervals", "montecarlo", "filters", "filtering"},
    {"report"},
    {"worlds"},
    {"config"},
    {"studies"},
    {"reproduce", "cli"},
    {"__init__"},
]
RANK = {part: i for i, layer in enumerate(LAYERS) for part in layer}
ROOT = Path(tracklab.__file__).parent


def _part(module: str) -> str:
    """The top-level part of the package a dotted module name belongs to."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "__init__"


def _imports(tree):
    """Every tracklab module a file imports, at any depth (lazy imports inside functions too)."""
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            yield from (a.name for a in node.names if a.name.split(".")[0] == "tracklab")
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and (node.module or "").split(".")[0] == "tracklab":
            if node.module == "tracklab":  # from tracklab import random -> tracklab.random
                yield from (f"tracklab.{a.name}" for a in node.names if a.name != "__version__")
            else:
                yield node.module


def test_every_part_of_the_package_has_a_layer():
    parts = {p.relative_to(ROOT).parts[0].removesuffix(".py") for p in ROOT.rglob("*.py")}
    assert parts <= set(RANK), sorted(parts - set(RANK))


def test_imports_go_downward_only():
    upward = []
    for f in sorted(ROOT.rglob("*.py")):
        me = f.relative_to(ROOT).parts[0].removesuffix(".py")
        for module in _imports(ast.parse(f.read_text())):
            target = _part(module)
            if target in RANK and RANK[target] > RANK[me]:
                upward.append(f"{f.relative_to(ROOT)} imports {module}")
    assert not upward, "\n".join(upward)


def test_the_layer_check_catches_an_upward_import():
    tree = ast.parse("def f():\n    from tracklab.config import load_experiment\n")
    assert RANK[_part(next(_imports(tree)))] > RANK["worlds"]


def test_the_package_and_the_command_module_import_nothing_heavy():
    probe = ("import sys, tracklab, tracklab.cli; "
             "print(' '.join(sorted(m for m in sys.modules if m.split('.')[0] in ('jax', 'numpy', 'tracklab'))))")
    r = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    imported = r.stdout.split()
    assert "tracklab.interrupts" in imported and not any(m.split(".")[0] in ("jax", "numpy") for m in imported), imported
    assert not {"tracklab.output", "tracklab.processes", "tracklab.runtime", "tracklab.config"} & set(imported), imported
    own = {a.name for node in ast.parse((ROOT / "interrupts.py").read_text()).body
           if isinstance(node, (ast.Import, ast.ImportFrom)) for a in node.names}
    assert own <= {"annotations", "signal", "sys"}, own


def test_the_public_names_are_served_as_if_imported():
    from tracklab.filtering import run_filter
    from tracklab.studies.tune import tune

    assert set(tracklab.__all__) <= set(dir(tracklab))
    for name in tracklab.__all__:
        assert getattr(tracklab, name) is not None, name
    assert tracklab.run_filter is run_filter and tracklab.tune is tune
    assert tracklab.filters.__name__ == "tracklab.filters"
    ns = {}
    exec("from tracklab import *", ns)
    assert set(tracklab.__all__) <= set(ns)
    with pytest.raises(AttributeError, match="no_such_name"):
        tracklab.no_such_name
