"""Sweeps: one vmapped call over a grid of scale factors, equal to separate runs."""

import json
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from tracklab.config import load_experiment
from tracklab.montecarlo.statistics import statistics
from tracklab.config.paths import parse_grid
from tracklab.studies.sweep import sweep

from test_cli import in_process

EXP = """
[experiment]
name = "mismatch"
runs = 96
dt = 0.5
steps = 40

[scenario]
kind = "crossing"

[sensor]
kind = "polar"
sigma_r = 100.0
sigma_angle = 0.003

[[filter]]
kind = "ekf"
label = "EKF"

[[filter]]
kind = "cmkf"
label = "CMKF"
debias = "unbiased"

[report]
window = [5, 40]
"""


def test_sweep_point_equals_a_separate_run_with_scaled_parameters(tmp_path):
    path = tmp_path / "exp.toml"
    path.write_text(textwrap.dedent(EXP))
    exp = load_experiment(path)
    doc = sweep(exp, [parse_grid("q=0.01:100:3"), parse_grid("r=0.2:5:2")], chunk=40, block_points=4)
    assert len(doc["points"]) == 6
    for point in (doc["points"][0], doc["points"][5]):
        f = point["values"]
        one = load_experiment(path)
        for fc in one.filters:
            fc.params["q"] = fc.params["q"] * f["q"]
            fc.params["r"] = tuple(v * f["r"] for v in fc.params["r"])
        st = statistics(one.monte_carlo(), one.window)
        for label in ("EKF", "CMKF"):
            a, b = point["stats"]["filters"][label]["summary"], st["filters"][label]["summary"]
            for k in ("rmse_pos", "rmse_vel", "nees", "max_err_pos", "nis"):
                np.testing.assert_allclose(a[k], b[k], rtol=1e-9, err_msg=f"{label} {k} at {f}")
    # mismatch shows: Q 100x too small is over-confident, R 5x too large under-confident
    nees = {tuple(p["values"].values()): p["stats"]["filters"]["EKF"]["summary"]["nees"] for p in doc["points"]}
    assert nees[(0.01, 0.2)] > 4.5 and nees[(100.0, 5.0)] < 3.0


@pytest.mark.parametrize("spec", ["q=1:2", "q-2=1:2:3", "q=0:1:3", "q=2:1:3", "q=1:2:0"])
def test_bad_grids_are_refused(spec):
    with pytest.raises(ValueError):
        parse_grid(spec)


def test_cli_sweep(tmp_path, monkeypatch, capsys):
    path = tmp_path / "exp.toml"
    path.write_text(textwrap.dedent(EXP))
    proc = subprocess.run([sys.executable, "-m", "tracklab.cli", "sweep", str(path), "--grid", "q=0.1:10:2",
                           "--runs", "16", "--out", str(tmp_path / "sw")], capture_output=True, text=True, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    for f in ("sweep.json", "table.md", "table.csv", "sweep_rmse_pos.png", "sweep_nees.png"):
        assert (tmp_path / "sw" / f).exists(), f
    for grid in ("q=1:2", "zeta=1:2:3"):  # malformed; a parameter no filter here declares
        bad = in_process("sweep", path, "--grid", grid, cwd=tmp_path, monkeypatch=monkeypatch, capsys=capsys)
        assert bad.returncode == 2 and bad.stderr.startswith("error:") and "--grid" in bad.stderr
        assert len(bad.stderr.splitlines()) == 1


def test_a_curve_that_barely_moves_is_drawn_flat():
    """A sweep curve whose values change by a fraction of a percent gets a linear axis at least
    ±10 % about them (a log axis scaled to the data would fill the panel); a decade or more: log."""
    from tracklab.report.figures import pyplot
    from tracklab.report.sweep import value_axis

    plt = pyplot()
    fig, (flat, steep) = plt.subplots(1, 2)
    value_axis(flat, np.array([2.6113, 2.6114, 2.6139]), positive=True)
    value_axis(steep, np.array([2.4, 40.0, 1100.0]), positive=True)
    lo, hi = flat.get_ylim()
    assert flat.get_yscale() == "linear" and lo <= 2.6126 * 0.9 and hi >= 2.6126 * 1.1
    assert steep.get_yscale() == "log"
    plt.close(fig)


HONEST = """
[experiment]
name = "honest"
runs = 24
dt = 0.5
steps = 20

[scenario]
kind = "crossing"

[sensor]
kind = "polar"
sigma_r = 100.0
sigma_angle = 0.003

[[filter]]
kind = "ekf"
label = "EKF"
"""


@pytest.mark.parametrize("grid", ["experiment.runs=8:24:2", "experiment.seed=0:1:2", "report.level=0.5:0.99:2",
                                  "experiment.dt=0.25:0.5:2", "sensor.p_detect=0.5:1:2", "sensor.period=0.5:1:2"])
def test_every_axis_means_what_it_says(tmp_path, grid):
    """Each grid point's statistics are those of a plain run of the file with that value: the run
    count, the seed and the level too (not the file's, relabelled), and a value that changes the
    program (dt, a sensor's detection or report pattern) runs a program of its own."""
    import copy

    from tracklab.config import parse_experiment
    from tracklab.config.paths import set_value

    path = tmp_path / "honest.toml"
    path.write_text(textwrap.dedent(HONEST))
    exp = load_experiment(path)
    axis = parse_grid(grid)
    doc = sweep(exp, [axis])
    points = [p["stats"]["filters"]["EKF"] for p in doc["points"]]
    for value, got in zip(axis.values, points):
        raw = copy.deepcopy(exp.raw)
        set_value(raw, axis.path, value)
        want = parse_experiment(path, raw).simulate()["filters"]["EKF"]
        for part in ("summary", "half_width"):  # the numbers and their intervals (at the point's level)
            for k, v in want[part].items():
                if isinstance(v, (int, float)):
                    np.testing.assert_allclose(got[part][k], v, rtol=1e-9, atol=1e-12, err_msg=f"{grid} at {value}: {k}")
    assert (points[0]["summary"], points[0]["half_width"]) != (points[1]["summary"], points[1]["half_width"])


def test_a_sweep_of_three_axes_says_it_draws_no_figures(tmp_path, monkeypatch, capsys):
    """Figures draw one or two axes: a sweep of three says, in one line on stdout beside where its
    folder is written, which it did not draw and why (and nothing of it with --no-figures)."""
    path = tmp_path / "exp.toml"
    path.write_text(textwrap.dedent(EXP).replace("runs = 96", "runs = 4").replace("steps = 40", "steps = 8")
                    .replace("window = [5, 40]", "window = [2, 8]"))
    grid = ["--grid", "q=0.5:2:2", "--grid", "r=0.5:2:2", "--grid", "experiment.seed=0:1:2"]
    proc = in_process("sweep", path, *grid, "--out", tmp_path / "sw", cwd=tmp_path, monkeypatch=monkeypatch,
                      capsys=capsys)
    assert proc.returncode == 0, proc.stderr
    line = ("no figures: a sweep of 3 axes is written to sweep.json, table.md and table.csv only; "
            "figures draw 1 or 2 axes")
    assert proc.stdout.splitlines()[-2:] == [line, f"sweep written to {tmp_path / 'sw'}/"], proc.stdout
    written = {p.name for p in (tmp_path / "sw").iterdir()}
    assert {"sweep.json", "table.csv", "table.md"} <= written and not any(n.endswith(".png") for n in written)
    quiet = in_process("sweep", path, *grid, "--out", tmp_path / "sw2", "--no-figures", cwd=tmp_path,
                       monkeypatch=monkeypatch, capsys=capsys)
    assert quiet.returncode == 0 and "no figures" not in quiet.stdout + quiet.stderr, quiet.stdout


def test_a_sweep_table_gives_lost_tracks_with_their_wilson_interval(tmp_path):
    """In clutter a sweep's table shows each point's fraction of lost tracks with the Wilson
    interval its run shows (table.md), the bounds as columns of table.csv, and keeps them in
    sweep.json; the caption says what they are."""
    import csv
    from types import SimpleNamespace

    from tracklab.report.sweep import _write_sweep

    def stats(p, lo, hi):
        summary = {"p_lost": p, "lost": int(p * 100), "validated_per_scan": 1.2, "rmse_pos": 10.0, "rmse_vel": 1.0,
                   "pred_err_rms": 11.0, "nees": 4.1, "nees_in_bounds": 0.9, "diverged": 0}
        return {"level": 0.95, "filters": {"PDAF": {"kind": "pdaf", "summary": summary,
                                                    "half_width": {"rmse_pos": 0.3}, "intervals": {"p_lost": [lo, hi]}}}}

    doc = {"axes": {"sensor.p_detect": [0.8, 0.9]}, "titles": {"sensor.p_detect": "sensor.p_detect"}, "runs": 100,
           "wall_s": 1.0, "compile_s": 1.0,
           "points": [{"values": {"sensor.p_detect": 0.8}, "stats": stats(0.2, 0.133, 0.289)},
                      {"values": {"sensor.p_detect": 0.9}, "stats": stats(0.05, 0.022, 0.112)}]}
    exp = SimpleNamespace(name="clutter", window=(1, 10), raw={}, path=None)
    _write_sweep(exp, doc, tmp_path, figures=False)
    table = (tmp_path / "table.md").read_text()
    assert "| 20 % (13–29 %) |" in table and "| 5 % (2.2–11 %) |" in table and "Wilson interval" in table, table
    rows = list(csv.DictReader((tmp_path / "table.csv").open()))
    assert [(r["p_lost"], r["p_lost_lo"], r["p_lost_hi"]) for r in rows] == [("0.2", "0.133", "0.289"),
                                                                          ("0.05", "0.022", "0.112")]
    kept = json.loads((tmp_path / "sweep.json").read_text())
    assert kept["points"][1]["filters"]["PDAF"]["intervals"] == {"p_lost": [0.022, 0.112]}
