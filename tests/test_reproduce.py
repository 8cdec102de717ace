"""tracklab reproduce and tracklab table."""

import csv
import json
import subprocess
import sys
import textwrap

from tracklab.reproduce import BEGIN, END, combined_table, reproduce

SMALL = """
[experiment]
name = "NAME"
runs = 12
ALSO
dt = 1.0
steps = 15

[scenario]
kind = "constant_velocity"
initial = [0.0, 10.0]
accel_sigma = 1.0

[sensor]
kind = "cartesian"
sigma = 5.0

[[filter]]
kind = "kf"
label = "KF"

[[filter]]
kind = "alpha_beta"
label = "AB"

[report]
figures = ["rmse"]            # the figure the test looks for; every kind is drawn in tests/test_figures.py
"""


STUDIES = """

[[study]]
kind = "tune"
params = ["q"]
filters = ["KF"]
loss = "nll"
steps = 3
lr = 0.1
runs_per_step = 8
out = "tuning/kf"

[[study]]
kind = "sweep"
grid = ["q=0.1:10:3"]
runs = 6
out = "mismatch/c"
"""


def _experiments(tmp_path, studies=False):
    d = tmp_path / "experiments"
    d.mkdir()
    (d / "a.toml").write_text(textwrap.dedent(SMALL.replace("NAME", "a").replace("ALSO", "also_runs = [5]")))
    (d / "b.toml").write_text(textwrap.dedent(SMALL.replace("NAME", "b").replace("ALSO", "")) + (STUDIES if studies else ""))
    return d


def test_reproduce_runs_everything_and_rebuilds_the_combined_table(tmp_path):
    """Every experiment (and its extra run counts), the [[study]] tables an experiment names
    (the tuned file, its log and its run; the sweep folder), and the table between the markers."""
    import tomllib

    from tracklab.config import load_experiment
    from tracklab.reproduce import update_readme

    d = _experiments(tmp_path, studies=True)
    res = tmp_path / "results"
    res.mkdir()
    (res / "README.md").write_text(f"# Results\n\nprose stays\n\n{BEGIN}\nold\n{END}\n\nmore prose\n")
    folders = reproduce(d, res, log=lambda *a: None)
    assert [f.name for f in folders] == ["a", "b", "a_5runs"]
    for f in folders:
        assert (f / "stats.json").exists() and (f / "rmse.png").exists()
    text = (res / "README.md").read_text()
    assert "prose stays" in text and "more prose" in text and "old" not in text
    assert text.count(BEGIN) == 1 and "| a | KF |" in text and "| a_5runs | KF |" in text  # rows named by folder
    update_readme(res / "README.md", "| new |\n")  # again: the block is replaced, not appended
    text = (res / "README.md").read_text()
    assert text.count(BEGIN) == 1 and "| new |" in text and "| a | KF |" not in text and "more prose" in text
    # the studies of b.toml
    tuned = res / "tuning" / "kf_tuned.toml"
    assert load_experiment(tuned).filters[0].label == "KF, tuned"
    assert tomllib.loads(tuned.read_text())["filter"][0]["accel_sigma"] != 1.0
    log = (res / "tuning" / "kf_tune" / "tune.log").read_text()
    assert "step     0" in log and "KF: held-out nll" in log
    assert (res / "tuning" / "kf_tune" / "loss.png").exists()
    assert (res / "tuning" / "kf_tuned" / "stats.json").exists()
    sweep_table = (res / "mismatch" / "c" / "table.md").read_text()
    assert sweep_table.count("| KF |") == 3 and sweep_table.count("| AB |") == 3
    # again, into the folders it wrote (results, tuning report, tuned file, sweep), without figures: the same numbers
    before = {p.relative_to(res): p.read_text() for p in res.rglob("*.json")}
    assert reproduce(d, res, log=lambda *a: None, figures=False) == folders
    after = {p.relative_to(res): p.read_text() for p in res.rglob("*.json")}
    assert after.keys() == before.keys() and len(before) >= 6
    assert not list(res.rglob("*.png"))  # the folders written again hold no figure of the first pass
    strip = lambda doc: {k: v for k, v in json.loads(doc).items() if k not in ("wall_s", "compile_s")}
    for name in before:
        assert strip(after[name]) == strip(before[name]), name


def test_table_formats(tmp_path):
    d = _experiments(tmp_path)
    folders = reproduce(d, tmp_path / "r", quick=True, log=lambda *a: None, figures=False)
    assert not list((tmp_path / "r").rglob("*.png"))
    md = combined_table(folders, "md", ("rmse_pos", "runs"))
    assert md.splitlines()[0] == "| results | filter | RMSE pos | runs |" and len(md.splitlines()) == 2 + 4
    csv = combined_table(folders, "csv", ("rmse_pos",))
    assert csv.splitlines()[0] == "results,filter,rmse_pos,rmse_pos_hw"  # the interval's half-width beside it
    assert " ± " in md.splitlines()[2]
    tex = combined_table(folders, "latex", ("nees_in_bounds",))
    assert tex.startswith("\\begin{tabular}") and "\\%" in tex
    proc = subprocess.run([sys.executable, "-m", "tracklab.cli", "table", *map(str, folders), "--metrics", "nope"],
                          capture_output=True, text=True)
    assert proc.returncode == 2 and proc.stderr.startswith("error:") and "--metrics" in proc.stderr



def _stats(folder, filters):
    """A results folder whose stats.json holds ``filters`` (label -> (summary, half-widths))."""
    folder.mkdir()
    doc = {"name": folder.name, "runs": 8, "units": ["m", "m/s"], "wall_s": 1.5,
           "filters": {label: {"kind": "ekf", "summary": summary, "half_width": hw,
                               "intervals": {"diverged_fraction": [0.68, 1.0]}}
                       for label, (summary, hw) in filters.items()}}
    (folder / "stats.json").write_text(json.dumps(doc))
    return folder


def _cells(line, fmt):
    if fmt == "csv":
        return next(csv.reader([line]))
    if fmt == "latex":
        return [c.strip() for c in line.removesuffix("\\\\").split(" & ")]
    return [c.strip() for c in line.strip().strip("|").split(" | ")]


def test_table_shows_no_statistic_of_a_filter_with_no_healthy_run(tmp_path, monkeypatch, capsys):
    """A filter whose runs all diverged: every statistic of it is missing in every format, as the
    run's own table shows them, also where its stats.json holds numbers; a healthy one's are shown."""
    from test_cli import in_process

    numbers = {"rmse_pos": 12.5, "rmse_vel": 3.25, "max_err_pos": 40.0, "pred_err_rms": 20.0, "mean_err_x": 0.5,
               "mean_err_y": -0.5, "nees": 4.5, "nees_in_bounds": 0.75, "rmse_pos_over_pcrlb": 1.25,
               "max_track_err": 1.5, "random_err": 2.5}
    hw = dict.fromkeys(numbers, 0.25)
    folder = _stats(tmp_path / "r", {
        "numbers": ({**numbers, "diverged": 8, "runs": 8}, hw),
        "written": ({**dict.fromkeys(numbers), "diverged": 8, "runs": 8}, dict.fromkeys(hw)),  # as tracklab run writes it
        "healthy": ({**numbers, "diverged": 0, "runs": 8}, hw)})
    for fmt in ("md", "csv", "latex"):
        proc = in_process("table", folder, "--format", fmt, cwd=tmp_path, monkeypatch=monkeypatch, capsys=capsys)
        assert proc.returncode == 0 and not proc.stderr, proc.stderr
        rows = {c[1]: c for c in (_cells(line, fmt) for line in proc.stdout.splitlines()) if len(c) > 16}
        for label in ("numbers", "written"):
            assert rows[label][:3] == ["r", label, "m, m/s"] and rows[label][14:17] == ["8", "8", "1.5"], (fmt, rows[label])
            assert all(c in ("—", "") for c in rows[label][3:14] + rows[label][17:]), (fmt, rows[label])
        assert rows["healthy"][3].startswith("12.5") and rows["healthy"][14] == "0", (fmt, rows["healthy"])
