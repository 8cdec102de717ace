"""The ``tracklab`` command, run as a separate process (its options, and bad input refused in one line)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from tracklab.report.document import read_results

STEPS = 10
WINDOW = [3, 10]
LABELS = ("EKF main", "CMKF debiased")

VALID = f"""
[experiment]
name = "small"
runs = 40
seed = 0
dt = 0.5
steps = {STEPS}

[scenario]
kind = "crossing"

[sensor]
kind = "polar"
sigma_r = 100.0
sigma_angle = 0.003

[[filter]]
kind = "ekf"
label = "{LABELS[0]}"

[[filter]]
kind = "cmkf"
label = "{LABELS[1]}"
debias = "unbiased"

[report]
window = {WINDOW}
"""

SUMMARY_KEYS = ("rmse_pos", "rmse_vel", "max_err_pos", "nees", "nees_in_bounds")
SERIES_KEYS = ("rmse_pos", "rmse_vel", "max_err_pos", "nees")
PNGS = ("rmse.png", "mean_error.png", "nees.png")


def _command():
    script = Path(sys.executable).parent / "tracklab"
    if script.is_file() and os.access(script, os.X_OK):
        return [str(script)]
    return [sys.executable, "-m", "tracklab.cli"]


def tracklab(*args, cwd, timeout=300):
    return subprocess.run([*_command(), *map(str, args)], cwd=cwd, capture_output=True, text=True,
                          timeout=timeout)


def in_process(*args, cwd, monkeypatch, capsys):
    """``tracklab ARGS`` as the command's ``main`` in this process (the process around it is
    ``sys.exit(main())``): a CompletedProcess with its exit code and what it printed."""
    from tracklab.cli import main

    monkeypatch.chdir(cwd)
    capsys.readouterr()
    try:
        code = main([str(a) for a in args])
    except SystemExit as e:  # argparse's refusals
        code = e.code
    out, err = capsys.readouterr()
    return subprocess.CompletedProcess(args, code, out, err)


def tracklab_parallel(arg_lists, *, cwd, timeout=300):
    procs = [
        subprocess.Popen([*_command(), *map(str, args)], cwd=cwd, text=True,
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        for args in arg_lists
    ]
    done = []
    for p, args in zip(procs, arg_lists):
        out, err = p.communicate(timeout=timeout)
        done.append(subprocess.CompletedProcess(args, p.returncode, out, err))
    return done


def snapshot(folder: Path) -> dict:
    """Every path under ``folder`` -> its bytes (None for folders)."""
    return {
        str(p.relative_to(folder)): (None if p.is_dir() else p.read_bytes())
        for p in sorted(folder.rglob("*"))
    }


def leftovers(folder: Path) -> list[str]:
    return [str(p) for p in folder.rglob("*") if ".tmp-" in p.name or ".old-" in p.name]


def numbers(stats: dict) -> dict:
    """The statistics of a stats.json, without timings."""
    return {label: {"summary": f["summary"], "series": f["series"]} for label, f in stats["filters"].items()}


@pytest.fixture(scope="module")
def valid_run(tmp_path_factory):
    """One full run with figures, shared by the tests that only read its output."""
    root = tmp_path_factory.mktemp("valid")
    (root / "small.toml").write_text(VALID)
    proc = tracklab("run", "small.toml", "--runs", 20, "--out", "out", cwd=root)
    return root, proc


# --- a valid run -------------------------------------------------------------------------------


def test_run_exits_0_and_prints_the_table(valid_run):
    root, proc = valid_run
    assert proc.returncode == 0, proc.stderr
    assert "Traceback" not in proc.stderr
    for label in LABELS:
        assert label in proc.stdout
    lines = proc.stdout.splitlines()
    head = next(line for line in lines if line.startswith("filter "))  # the key columns, aligned
    assert "RMSE pos (m)" in head and max(map(len, lines[lines.index(head):])) <= 160
    assert all(len(line) <= 120 for line in lines[lines.index(head):lines.index(head) + 1 + len(LABELS)])
    assert "table.md" in proc.stdout and "| filter | kind |" in (root / "out" / "table.md").read_text()
    assert "20 runs" in proc.stdout  # --runs overrides the file's 40
    assert "compiling" not in proc.stderr and "running" not in proc.stderr  # not a terminal: no phases, no bar


def test_run_writes_the_results_folder(valid_run):
    root, proc = valid_run
    assert proc.returncode == 0, proc.stderr
    out = root / "out"
    for name in ("stats.json", "table.md", "table.csv", *PNGS):
        assert (out / name).is_file(), name
    for name in PNGS:
        data = (out / name).read_bytes()
        assert data.startswith(b"\x89PNG\r\n\x1a\n") and len(data) > 1000, name
    table_md = (out / "table.md").read_text()
    table_csv = (out / "table.csv").read_text().splitlines()
    assert table_csv[0].startswith("filter,kind,")
    for label in LABELS:
        assert label in table_md
        assert any(row.startswith(f"{label},") for row in table_csv[1:])
    assert leftovers(root) == []


def test_stats_json_contract(valid_run):
    root, proc = valid_run
    assert proc.returncode == 0, proc.stderr
    stats = read_results(root / "out")
    assert isinstance(stats["filters"], dict)
    assert list(stats["filters"]) == list(LABELS)
    assert stats["runs"] == 20 and stats["steps"] == STEPS
    assert "tracklab_version" in stats and stats["experiment"]["experiment"]["name"] == "small"
    kinds = {}
    lo, hi = WINDOW[0] - 1, WINDOW[1]
    for label, f in stats["filters"].items():
        kinds[label] = f["kind"]
        assert f["label"] == label
        s, series = f["summary"], f["series"]
        for key in SUMMARY_KEYS:
            assert isinstance(s[key], (int, float)) and np.isfinite(s[key]), (label, key)
        assert 0.0 <= s["nees_in_bounds"] <= 1.0
        assert s["rmse_pos"] > 0 and s["rmse_vel"] > 0
        for key in SERIES_KEYS:
            assert isinstance(series[key], list) and len(series[key]) == STEPS, (label, key)
            assert all(isinstance(v, (int, float)) for v in series[key]), (label, key)
        # the summary is the series reduced over the report window
        nees = np.array(series["nees"][lo:hi])
        assert s["nees"] == pytest.approx(nees.mean(), rel=1e-9)
        assert s["max_err_pos"] == pytest.approx(max(series["max_err_pos"][lo:hi]), rel=1e-9)
        inside = (nees >= np.array(series["nees_lo"][lo:hi])) & (nees <= np.array(series["nees_hi"][lo:hi]))
        assert s["nees_in_bounds"] == pytest.approx(inside.mean())
    assert kinds == {LABELS[0]: "ekf", LABELS[1]: "cmkf"}


def test_series_has_every_summary_quantity(valid_run, tmp_path):
    """Every summary has its per-step series in the folder (nees_in_bounds: the NEES and its band,
    from which test_stats_json_contract recomputes it); the series are in series.npz, which
    numpy.load reads, and a string of the file's own that reads like the mark stays a string."""
    import json

    from tracklab.report.document import SERIES_MARK, split_series, write_series

    root, _ = valid_run
    stats = read_results(root / "out")
    for f in stats["filters"].values():
        for key in (*SERIES_KEYS, "nees_lo", "nees_hi"):
            assert len(f["series"][key]) == STEPS, key
    lean, arrays = split_series({"label": SERIES_MARK, "series": {"x": np.arange(40.0)}})
    (tmp_path / "stats.json").write_text(json.dumps(lean))
    write_series(tmp_path / "series.npz", arrays)
    back = read_results(tmp_path)
    assert back["label"] == SERIES_MARK and np.array_equal(back["series"]["x"], np.arange(40.0))
    with np.load(tmp_path / "series.npz") as npz:
        assert npz[json.dumps(["series", "x"])].dtype == np.float32


def test_plot_draws_again_from_the_folder_and_keeps_the_rest(valid_run, tmp_path, monkeypatch, capsys):
    """`tracklab plot`: other formats and kinds from the stored statistics, every other file as it
    was; a bad kind, a folder that is not a run's, and one holding a file of the user's refused
    in one line, nothing changed."""
    import json
    import shutil

    root, _ = valid_run
    folder = tmp_path / "copy"
    shutil.copytree(root / "out", folder)
    kept = {p.name: p.read_bytes() for p in folder.iterdir() if p.name != ".tracklab-files"}
    proc = in_process("plot", "copy", "--format", "pdf", "--figures", "rmse,track", cwd=tmp_path,
                      monkeypatch=monkeypatch, capsys=capsys)
    assert proc.returncode == 0, proc.stderr
    assert "rmse.pdf, track.pdf" in proc.stdout
    assert (folder / "rmse.pdf").read_bytes().startswith(b"%PDF") and not (folder / "nees.pdf").exists()
    assert all((folder / name).read_bytes() == data for name, data in kept.items())
    assert {"rmse.pdf", "track.pdf"} <= set(json.loads((folder / ".tracklab-files").read_text())["files"])
    (folder / "mine.txt").write_text("mine")
    for args, field in ((("copy", "--figures", "rmse,bogus"), "bogus"), (("copy",), "tracklab did not write"),
                        ((".",), "stats.json")):
        proc = in_process("plot", *args, cwd=tmp_path, monkeypatch=monkeypatch, capsys=capsys)
        assert proc.returncode == 2 and len(proc.stderr.splitlines()) == 1 and field in proc.stderr, proc.stderr
    assert (folder / "mine.txt").read_text() == "mine" and leftovers(tmp_path) == []


def test_phases_and_bars_on_a_terminal(monkeypatch):
    """On a terminal: each phase a line, the runs' bar and a training's bar (with its loss), the
    elapsed time at the end; --quiet or no terminal: nothing."""
    import io

    from tracklab import progress

    class Terminal(io.StringIO):
        def isatty(self):
            return True

    err = Terminal()
    monkeypatch.setattr(sys, "stderr", err)
    assert progress.wanted(False) and not progress.wanted(True)
    phases = progress.Phases("small", progress.wanted(False))
    phases.phase("compiling the program")
    phases.train("DEKF", 3, 3, 0.25)
    phases.progress(40, 100)
    phases.progress(100, 100)
    phases.done("done")
    text = err.getvalue()
    for part in ("small: compiling the program\n", "small: training DEKF", "3/3", "loss 0.25", "small: running",
                 "100/100", "small: done ("):
        assert part in text, (part, text)
    monkeypatch.setattr(sys, "stderr", io.StringIO())
    assert not progress.wanted(False)


# --- seeds ------------------------------------------------------------------------------------


def test_seed_reproducible_and_changes_numbers(valid_run, tmp_path):
    root, proc = valid_run
    assert proc.returncode == 0, proc.stderr
    first = numbers(read_results(root / "out"))  # the file's seed, 0
    # the two runs are independent processes: run them side by side
    again, other = tracklab_parallel(
        [("run", root / "small.toml", "--runs", 20, "--seed", 0, "--out", "same", "--no-figures"),
         ("run", root / "small.toml", "--runs", 20, "--seed", 7, "--out", "other", "--no-figures")],
        cwd=tmp_path,
    )
    assert again.returncode == 0, again.stderr
    assert other.returncode == 0, other.stderr
    assert numbers(read_results(tmp_path / "same")) == first
    changed = numbers(read_results(tmp_path / "other"))
    for label in LABELS:
        assert changed[label]["summary"]["rmse_pos"] != first[label]["summary"]["rmse_pos"]
        assert changed[label]["series"]["rmse_pos"] != first[label]["series"]["rmse_pos"]
    assert not (tmp_path / "same" / "rmse.png").exists()  # --no-figures


# --- bad input ----------------------------------------------------------------------------------
# The command's main in this process (``in_process``): each refusal is made there, and the process
# around it only exits with main's code. Refusals in a process of their own:
# test_out_is_an_existing_file, test_no_command_is_refused.


def _bad(text=None, csv=None, args=()):
    return {"text": text, "csv": csv, "args": tuple(args)}



BAD = [
    pytest.param(_bad(VALID.replace('kind = "cmkf"', 'kind = "particle"')), ["filter[2].kind", "'particle'"],
                 id="unknown-filter-kind"),
    pytest.param(_bad(VALID.replace("sigma_r = 100.0", "sigma_r = -100.0")), ["sensor.sigma_r", "-100.0"],
                 id="negative-sigma"),
    pytest.param(_bad("[experiment\nname = 'x'\n"), ["file", "not valid TOML"], id="invalid-toml"),
    pytest.param(_bad(None), ["missing.toml", "does not exist"], id="missing-file"),
    pytest.param(_bad(VALID.replace('kind = "crossing"', 'kind = "trajectory"\npath = "flight.csv"'),
                      csv="t,x,y,z\n0,1,2,3\n"),
                 ["scenario.path", "'flight.csv'", "at least 2"], id="short-trajectory-csv"),
    pytest.param(_bad(VALID, args=("--runs", 10**11)), ["--runs", str(10**11)], id="runs-too-large"),
    pytest.param(_bad(VALID.replace("[report]", '[report]\nfigures = ["rmse", "trak"]')),
                 ["report.figures", "'trak'", "track_loss"], id="unknown-figure-kind"),
    pytest.param(_bad(VALID.replace("sigma_r = 100.0", "sigma_r = 1e200")), ["sensor.sigma_r", "1e+200"],
                 id="sigma-1e200"),
    pytest.param(_bad(VALID.replace("[report]", "[prior]\npos_sigma = 1e200\n\n[report]")),
                 ["prior.pos_sigma", "1e+200"], id="prior-1e200"),
]


@pytest.mark.parametrize("bad, expect", BAD)
def test_bad_file_one_line_exit_2_results_untouched(tmp_path, monkeypatch, capsys, bad, expect):
    exp = tmp_path / ("missing.toml" if bad["text"] is None else "bad.toml")
    if bad["text"] is not None:
        exp.write_text(bad["text"])
    if bad["csv"] is not None:
        (tmp_path / "flight.csv").write_text(bad["csv"])
    out = tmp_path / "results"
    (out / "nested").mkdir(parents=True)
    (out / "stats.json").write_text('{"filters": {"old": 1}}\n')
    (out / "table.md").write_bytes(b"| old |\r\n\x00binary\xff")
    (out / "nested" / "keep.txt").write_text("keep me")
    before_out, before_root = snapshot(out), sorted(p.name for p in tmp_path.iterdir())

    proc = in_process("run", exp.name, "--out", "results", "--no-figures", *bad["args"], cwd=tmp_path,
                      monkeypatch=monkeypatch, capsys=capsys)

    assert "Traceback" not in proc.stderr, proc.stderr
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.splitlines()
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith("error:")
    assert exp.name in lines[0]
    for s in expect:
        assert s in lines[0], (s, lines[0])
    assert snapshot(out) == before_out
    assert sorted(p.name for p in tmp_path.iterdir()) == before_root
    assert leftovers(tmp_path) == []


def test_out_is_an_existing_file(tmp_path):
    (tmp_path / "small.toml").write_text(VALID)
    (tmp_path / "notes.txt").write_text("precious")
    proc = tracklab("run", "small.toml", "--runs", 20, "--out", "notes.txt", "--no-figures", cwd=tmp_path)
    assert "Traceback" not in proc.stderr
    assert proc.returncode == 2
    assert proc.stderr.splitlines()[-1].startswith("error:") and "notes.txt" in proc.stderr
    assert (tmp_path / "notes.txt").read_text() == "precious"
    assert leftovers(tmp_path) == []


@pytest.mark.parametrize(
    "args",
    [
        pytest.param(("--runs", "0"), id="runs-0"),
        pytest.param(("--runs", "abc"), id="runs-abc"),
        pytest.param(("--runs", "-3"), id="runs-negative"),
        pytest.param(("--runs", "2.5"), id="runs-float"),
        pytest.param(("--seed", "-1"), id="seed-negative"),
        pytest.param(("--seed", "x"), id="seed-abc"),
    ],
)
def test_bad_arguments_refused_by_argparse(tmp_path, monkeypatch, capsys, args):
    (tmp_path / "small.toml").write_text(VALID)
    proc = in_process("run", "small.toml", *args, "--out", "out", cwd=tmp_path, monkeypatch=monkeypatch, capsys=capsys)
    assert proc.returncode == 2
    lines = proc.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: tracklab run:"), proc.stderr
    assert args[0] in proc.stderr and "Traceback" not in proc.stderr
    assert not (tmp_path / "out").exists()


def test_no_command_is_refused(tmp_path):
    proc = tracklab(cwd=tmp_path)
    assert proc.returncode == 2 and proc.stderr.startswith("error: tracklab:") and len(proc.stderr.splitlines()) == 1


# --- list -----------------------------------------------------------------------------------


def test_list(tmp_path):
    (tmp_path / "experiments").mkdir()
    (tmp_path / "experiments" / "small.toml").write_text(VALID)
    proc = tracklab("list", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    words = proc.stdout.split()
    for kind in ("kf", "ekf", "cmkf", "polar_kf", "sequential_ekf"):
        assert kind in words, kind
    for sensor in ("polar", "spherical", "cartesian"):
        assert sensor in words, sensor
    for target in ("sine", "cone"):  # a servo file's [target] kinds
        assert target in proc.stdout.split("servo targets")[1].split(), target
    assert "small.toml" in proc.stdout


# --- relative paths ----------------------------------------------------------------------------


def test_relative_trajectory_path_resolved_against_the_experiment_file(tmp_path):
    folder = tmp_path / "exps" / "sub"
    folder.mkdir(parents=True)
    rows = "".join(f"{t},{1000.0 + 150.0 * t},{2000.0 - 50.0 * t},{300.0 + 5.0 * t}\n" for t in range(6))
    (folder / "flight.csv").write_text("t,x,y,z\n" + rows)
    (folder / "traj.toml").write_text(
        """
[experiment]
name = "traj"
runs = 20
dt = 0.5
steps = 8

[scenario]
kind = "trajectory"
path = "flight.csv"

[sensor]
kind = "cartesian"
sigma = 10.0

[[filter]]
kind = "kf"
label = "KF"
"""
    )
    cwd = tmp_path / "elsewhere"
    cwd.mkdir()
    # a decoy: if the path were resolved against the working folder this file would be refused
    (cwd / "flight.csv").write_text("not,a,trajectory\n")
    proc = tracklab("run", Path("..") / "exps" / "sub" / "traj.toml", "--runs", 20, "--out", "res", "--no-figures",
                    cwd=cwd)
    assert proc.returncode == 0, proc.stderr
    assert "KF" in proc.stdout
    stats = read_results(cwd / "res")
    f = stats["filters"]["KF"]
    assert f["kind"] == "kf" and stats["steps"] == 8
    assert len(f["series"]["rmse_pos"]) == 8
    assert "rmse_z" in f["series"]  # 3-D
    assert np.isfinite(f["summary"]["rmse_pos"]) and 0 < f["summary"]["rmse_pos"] < 100
    assert not (folder / "res").exists() and not (tmp_path / "results").exists()


def test_interrupted_run_leaves_previous_results_intact(tmp_path):
    """Ctrl-C (SIGINT) part-way through a run: exit 130, no traceback, the old folder untouched."""
    import signal
    import time

    (tmp_path / "small.toml").write_text(VALID)
    out = tmp_path / "out"
    out.mkdir()
    previous = '{"tracklab_version": "0.1.0", "experiment": {}, "filters": {}}'  # a results folder of tracklab's
    (out / "stats.json").write_text(previous)
    # a terminal's Ctrl-C reaches a process whose SIGINT is at its default; a test worker (or any
    # background job) may hand its children an ignored SIGINT, so restore the default in the child
    # a cache folder of its own: the run stores its compiled program there, the sign that it is in its chunks
    env = {k: v for k, v in os.environ.items() if k != "JAX_COMPILATION_CACHE_DIR"}
    env["TRACKLAB_CACHE_DIR"] = str(tmp_path / "cache")
    proc = subprocess.Popen([*_command(), "run", "small.toml", "--runs", "100000000", "--out", "out", "--no-figures"],
                            cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    waited = 0.0
    while not list((tmp_path / "cache").glob("programs/*.program")) and waited < 60 and proc.poll() is None:
        time.sleep(0.1)
        waited += 0.1
    time.sleep(0.5)  # its first chunks
    proc.send_signal(signal.SIGINT)
    try:
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:  # never leave a 10⁸-run process behind
            proc.kill()
            proc.communicate()
    assert proc.returncode == 130, err
    assert "Traceback" not in err and "interrupted" in err
    assert (out / "stats.json").read_text() == previous
    assert sorted(p.name for p in out.iterdir()) == ["stats.json"]
    assert leftovers(tmp_path) == []


def test_a_reader_that_stops_reading_does_not_stop_the_command():
    """``tracklab run … | head -1``: once the pipe is closed what is printed is dropped, without an
    error (the results are written all the same)."""
    import os

    from tracklab.cli import _Reader

    read, write = os.pipe()
    os.close(read)
    stream = _Reader(open(write, "w", buffering=1))
    for _ in range(3):
        print("| a row of the table |", file=stream)
    stream.flush()
    assert stream.isatty() is False
    stream.stream.close()
