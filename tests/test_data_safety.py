"""Data safety and honest failure: outputs written only where they may, atomically; missing
statistics shown as missing; every bad input, path or size refused in one line before
anything compiles."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from tracklab import cli
from tracklab.config import load_experiment
from tracklab.errors import ConfigError
from tracklab.output import (HEADER_KEY, MANIFEST, atomic_folder, check_results_folder, check_tuned_file, clean_stale,
                             foreign_entries, temporary_name, temporary_of, write_text_atomically)

SMALL = """
[experiment]
name = "small"
runs = 6
seed = 0
dt = 1.0
steps = 6

[scenario]
kind = "constant_velocity"
initial = [0.0, 10.0, 0.0, 5.0]
accel_sigma = 1.0

[sensor]
kind = "cartesian"
sigma = 10.0

[[filter]]
kind = "kf"
label = "KF"
"""

TWO_SENSORS = """
[experiment]
name = "two"
runs = 6
dt = 1.0
steps = 6

[scenario]
kind = "constant_velocity"
initial = [0.0, 10.0, 0.0, 5.0]

[[sensor]]
kind = "cartesian"
name = "a"
sigma = 10.0

[[sensor]]
kind = "cartesian"
name = "b"
sigma = 20.0

[[filter]]
kind = "kf"
label = "KF"

[[filter]]
kind = "stf"
label = "STF"
"""

AIRBORNE = """
[experiment]
name = "air"
runs = 4

[airborne]
duration = 4.0

[[tracker]]
kind = "cd_ekf"
"""

SERVO = """
[experiment]
name = "servo"
runs = 2

[servo]
frames = 100
settle = 0.5

[target]
kind = "sine"

[[case]]
mode = "double_loop"
"""


def results_doc(**extra):
    return json.dumps({HEADER_KEY: "0.1.0", "name": "old", "filters": {"KF": {"kind": "kf", "summary": {}}}, **extra})


def make_results(folder: Path, text="previous"):
    """A folder as tracklab writes it (the header, a table, a figure)."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "stats.json").write_text(results_doc(note=text))
    (folder / "table.md").write_text(f"| {text} |\n")
    (folder / "rmse.png").write_bytes(b"\x89PNG\r\n\x1a\n" + text.encode())


def snapshot(folder: Path) -> dict:
    """Every path under ``folder`` -> its bytes (a link: its target; a folder: None)."""
    def value(p):
        if p.is_symlink():
            return "link to " + os.readlink(p)
        return None if p.is_dir() else p.read_bytes()

    return {str(p.relative_to(folder)): value(p) for p in sorted(folder.rglob("*"))}


def leftovers(folder: Path) -> list[str]:
    return [p.name for p in folder.rglob("*") if ".tmp-" in p.name or ".old-" in p.name]


def main(capsys, *args, cwd):
    """``tracklab ARGS`` in this process: (exit status, stdout, stderr lines)."""
    old = os.getcwd()
    os.chdir(cwd)
    try:
        code = cli.main([str(a) for a in args])
    except SystemExit as e:  # argparse's refusals
        code = e.code
    finally:
        os.chdir(old)
    out, err = capsys.readouterr()
    return code, out, err.strip().splitlines()


def refused(capsys, *args, cwd, expect=()):
    code, _, err = main(capsys, *args, cwd=cwd)
    assert code == 2, err
    assert len(err) == 1 and err[0].startswith("error:"), err
    for s in expect:
        assert s in err[0], (s, err[0])
    return err[0]


def dead_pid() -> int:
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


# --- --out: only where tracklab may write ----------------------------------------------------


@pytest.mark.parametrize("command", ["run", "sweep"])
def test_a_folder_tracklab_did_not_write_is_refused(tmp_path, capsys, command):
    (tmp_path / "small.toml").write_text(SMALL)
    user = tmp_path / "D"
    (user / "sub").mkdir(parents=True)
    (user / "precious.txt").write_text("x")
    before = snapshot(user)
    args = ["--grid", "q=0.5:2:2"] if command == "sweep" else []
    refused(capsys, command, "small.toml", "--out", "D", *args, cwd=tmp_path, expect=("--out", "did not write", "precious.txt"))
    assert snapshot(user) == before and leftovers(tmp_path) == []


def test_a_results_folder_with_a_users_file_in_it_is_refused(tmp_path, capsys):
    (tmp_path / "small.toml").write_text(SMALL)
    make_results(tmp_path / "out")
    (tmp_path / "out" / "notes.txt").write_text("mine")
    before = snapshot(tmp_path / "out")
    refused(capsys, "run", "small.toml", "--out", "out", cwd=tmp_path, expect=("notes.txt",))
    assert snapshot(tmp_path / "out") == before


@pytest.mark.parametrize("out, expect", [(".", "working folder"), ("..", "working folder"),
                                         ("exps", "experiment file")])
def test_the_working_or_experiment_folder_is_refused(tmp_path, capsys, out, expect):
    cwd = tmp_path / "work"
    (cwd / "exps" / "data").mkdir(parents=True)
    (cwd / "exps" / "small.toml").write_text(SMALL)
    (cwd / "exps" / "data" / "flight.csv").write_text("t,x,y,z\n")
    before = snapshot(tmp_path)
    refused(capsys, "run", "exps/small.toml", "--out", out, cwd=cwd, expect=(expect,))
    assert snapshot(tmp_path) == before


def test_unwritable_and_overlong_outputs_are_refused_before_compiling(tmp_path, capsys):
    (tmp_path / "small.toml").write_text(SMALL)
    (tmp_path / "file").write_text("a file")
    cases = [("file/sub", "not a folder"), ("x" * 250, "at most"), ("a/" + "y" * 300 + "/b", "longer than")]
    if sys.platform.startswith("linux"):
        cases += [("/proc/tracklab-x", "cannot be written"), ("/sys/tracklab-x", "cannot be written")]
    for out, expect in cases:
        refused(capsys, "run", "small.toml", "--out", out, cwd=tmp_path, expect=("--out", expect))
    (tmp_path / "dangling").symlink_to(tmp_path / "nowhere")
    refused(capsys, "run", "small.toml", "--out", "dangling", cwd=tmp_path, expect=("symbolic link to nothing",))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["dangling", "file", "small.toml"]


def test_tune_out_must_be_a_new_file_or_one_tune_wrote(tmp_path, capsys):
    (tmp_path / "small.toml").write_text(SMALL)
    (tmp_path / "folder").mkdir()
    (tmp_path / "mine.toml").write_text("# my notes\n")
    refused(capsys, "tune", "small.toml", "--params", "q", "--out", "folder", cwd=tmp_path, expect=("is a folder",))
    refused(capsys, "tune", "small.toml", "--params", "q", "--out", "mine.toml", cwd=tmp_path,
            expect=("not written by tracklab tune",))
    refused(capsys, "tune", "small.toml", "--params", "q", "--out", "small.toml", cwd=tmp_path,
            expect=("not written by tracklab tune",))
    assert (tmp_path / "mine.toml").read_text() == "# my notes\n"


# --- the atomic replacement --------------------------------------------------------------------


def test_atomic_folder_replaces_in_one_step_and_keeps_the_old_until_then(tmp_path):
    out = tmp_path / "res"
    make_results(out, "old")
    with atomic_folder(out) as tmp:
        (tmp / "stats.json").write_text(results_doc(note="new"))
        assert json.loads((out / "stats.json").read_text())["note"] == "old"  # untouched while writing
    assert json.loads((out / "stats.json").read_text())["note"] == "new"
    assert sorted(os.listdir(out)) == [MANIFEST, "stats.json"] and leftovers(tmp_path) == []
    with pytest.raises(RuntimeError), atomic_folder(out) as tmp:  # a failure part-way: nothing changes
        (tmp / "stats.json").write_text(results_doc(note="half"))
        raise RuntimeError
    assert json.loads((out / "stats.json").read_text())["note"] == "new" and leftovers(tmp_path) == []


def test_atomic_folder_through_a_symlink_keeps_the_link(tmp_path):
    real = tmp_path / "real"
    make_results(real, "old")
    (tmp_path / "link").symlink_to(real)
    with atomic_folder(tmp_path / "link") as tmp:
        (tmp / "stats.json").write_text(results_doc(note="new"))
    assert (tmp_path / "link").is_symlink()
    assert json.loads((real / "stats.json").read_text())["note"] == "new"
    assert leftovers(tmp_path) == []


def test_stale_temporaries_of_dead_processes_are_cleaned_and_a_lost_folder_restored(tmp_path):
    pid = dead_pid()
    out = tmp_path / "res"
    make_results(tmp_path / temporary_name("res", "old", pid), "kept")  # a kill fell between the two renames
    make_results(tmp_path / temporary_name("res", "tmp", pid), "half")
    cut = tmp_path / temporary_name("res", "tmp", dead_pid())  # killed while writing stats.json: the header, then nothing
    cut.mkdir()
    (cut / "stats.json").write_text('{"tracklab_version":"0.1.0","na')
    other = temporary_name("other", "tmp", pid)  # another output's: left alone
    make_results(tmp_path / other, "not ours")
    live = tmp_path / temporary_name("res", "tmp", os.getppid())  # a live process's: left alone
    make_results(live, "live")
    mine = tmp_path / temporary_name("res", "tmp", dead_pid())  # holding a user's file: never touched
    mine.mkdir()
    (mine / "notes.txt").write_text("precious")
    forged = temporary_name("res", "tmp", pid)
    forged = forged[:-1] + ("0" if forged[-1] != "0" else "1")  # a TOKEN whose check digits do not match
    unmarked = [f".res.tmp-{pid}", f".res.old-{pid}", forged]
    for name in unmarked:  # without tracklab's token (a user's, or an older tracklab's): never touched
        make_results(tmp_path / name, "a user's")
    clean_stale(out)
    assert json.loads((out / "stats.json").read_text())["note"] == "kept"
    assert sorted(os.listdir(tmp_path)) == sorted([other, live.name, mine.name, "res", *unmarked])
    assert (mine / "notes.txt").read_text() == "precious"


def test_foreign_entries_names_what_tracklab_did_not_write(tmp_path):
    make_results(tmp_path / "ok")
    assert foreign_entries(tmp_path / "ok") == []
    (tmp_path / "legacy").mkdir()  # written before the header existed
    (tmp_path / "legacy" / "stats.json").write_text('{"name": "x", "experiment": {}, "filters": {}}')
    assert foreign_entries(tmp_path / "legacy") == []
    (tmp_path / "fake").mkdir()
    (tmp_path / "fake" / "stats.json").write_text('{"filters": {"old": 1}}')
    assert foreign_entries(tmp_path / "fake") == ["stats.json"]
    (tmp_path / "empty").mkdir()
    assert check_results_folder(tmp_path / "empty", None) == (tmp_path / "empty").resolve()


def listed(folder: Path) -> list[str]:
    doc = json.loads((folder / MANIFEST).read_text())
    assert doc[HEADER_KEY]
    return doc["files"]


def test_a_results_folder_lists_what_tracklab_wrote_and_nothing_else_counts_as_its(tmp_path, capsys):
    """The manifest lists exactly what was written (figures included); a file of the user's
    dropped in, a PNG included, makes the folder one tracklab did not write: refused in one line
    before anything runs, and kept."""
    out = tmp_path / "out"
    with atomic_folder(out) as tmp:
        (tmp / "stats.json").write_text(results_doc(note="first"))
        (tmp / "table.md").write_text("| first |\n")
        (tmp / "rmse.png").write_bytes(b"\x89PNG first")
    assert listed(out) == ["rmse.png", "stats.json", "table.md"] and foreign_entries(out) == []
    with atomic_folder(out) as tmp:  # written again: what this write wrote, and no figure of the first
        (tmp / "stats.json").write_text(results_doc(note="second"))
    assert sorted(os.listdir(out)) == [MANIFEST, "stats.json"] and listed(out) == ["stats.json"]

    (out / "rmse.png").write_bytes(b"\x89PNG the user's own")  # a name tracklab uses, but not written here
    (out / "mine.png").write_bytes(b"\x89PNG the user's own")
    before = snapshot(out)
    assert foreign_entries(out) == ["mine.png", "rmse.png"]
    with pytest.raises(ConfigError, match="mine.png, rmse.png"):
        check_results_folder(out, None)
    with pytest.raises(ConfigError, match="did not write"), atomic_folder(out):
        raise AssertionError("not reached")
    (tmp_path / "small.toml").write_text(SMALL)
    refused(capsys, "run", "small.toml", "--out", "out", cwd=tmp_path, expect=("did not write", "mine.png"))
    assert snapshot(out) == before and leftovers(tmp_path) == []

    (out / "mine.png").unlink()
    (out / "rmse.png").unlink()
    (out / "stats.json").unlink()
    (out / "stats.json").mkdir()  # a listed name that is no longer the file tracklab wrote
    assert foreign_entries(out) == [MANIFEST, "stats.json"]
    (out / "stats.json").rmdir()
    (out / "stats.json").write_text(results_doc())
    (out / MANIFEST).write_text("[]")  # a manifest that is not tracklab's: not a folder tracklab wrote
    assert foreign_entries(out) == [MANIFEST]

    legacy = tmp_path / "legacy"  # an older tracklab's folder, without a manifest: its names count as today
    make_results(legacy)
    (legacy / "nees.png").write_bytes(b"\x89PNG")
    assert foreign_entries(legacy) == []
    with atomic_folder(legacy) as tmp:
        (tmp / "stats.json").write_text(results_doc(note="new"))
    assert sorted(os.listdir(legacy)) == [MANIFEST, "stats.json"]


def test_temporaries_carry_a_token_and_a_users_look_alike_is_never_removed(tmp_path):
    """Temporaries are created under fresh names (.NAME.tmp-PID-TOKEN) that never are an existing
    path, and only a path with tracklab's TOKEN is ever removed: a user's .res.tmp-<this PID>
    beside --out res survives a write, a failed write and the clean-up of stale ones."""
    pid = os.getpid()
    users = {}
    for name in (f".res.tmp-{pid}", f".res.old-{pid}", f".t.toml.tmp-{pid}"):
        (tmp_path / name).mkdir()
        (tmp_path / name / "stats.json").write_text(results_doc())  # looks like tracklab's, is the user's
        users[name] = snapshot(tmp_path / name)
    old_style = tmp_path / f".res.tmp-{dead_pid()}"  # a dead process's name without the TOKEN
    old_style.write_text("")
    seen = []
    with atomic_folder(tmp_path / "res") as tmp:
        seen.append(tmp.name)
        assert temporary_of(tmp.name) == ("res", "tmp", pid) and tmp.name.startswith(f".res.tmp-{pid}-")
        (tmp / "stats.json").write_text(results_doc(note="new"))
    with pytest.raises(RuntimeError), atomic_folder(tmp_path / "res") as tmp:
        seen.append(tmp.name)
        raise RuntimeError
    assert seen[0] != seen[1]
    write_text_atomically(tmp_path / "t.toml", "# written by tracklab tune\n")
    clean_stale(tmp_path / "res")
    for name, before in users.items():
        assert snapshot(tmp_path / name) == before, name
    assert old_style.exists()
    assert json.loads((tmp_path / "res" / "stats.json").read_text())["note"] == "new"
    assert sorted(p.name for p in tmp_path.iterdir() if temporary_of(p.name)) == []


def test_the_longest_name_allowed_leaves_room_for_the_temporary_name(tmp_path):
    from tracklab.output import TEMP_SUFFIX

    limit = os.pathconf(tmp_path, "PC_NAME_MAX")
    longest = "r" * (limit - 1 - TEMP_SUFFIX)
    with atomic_folder(tmp_path / longest) as tmp:  # the temporary's name fits
        assert len(tmp.name) <= limit
        (tmp / "stats.json").write_text(results_doc())
    assert check_tuned_file(tmp_path / (longest[:-5] + ".toml"), None)
    with pytest.raises(ConfigError, match=f"at most {len(longest)} bytes"):
        check_results_folder(tmp_path / (longest + "r"), None)


def _mount_tmpfs(where: Path, options: str):
    where.mkdir()
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(where)], capture_output=True, text=True)
    if r.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here ({r.stderr.strip() or r.returncode}): needs root")


def test_full_disk_is_one_line_exit_1_previous_results_intact(tmp_path, capsys):
    disk = tmp_path / "disk"
    _mount_tmpfs(disk, "size=48k")
    try:
        (tmp_path / "small.toml").write_text(SMALL)
        make_results(disk / "out", "previous")
        before = snapshot(disk / "out")
        code, _, err = main(capsys, "run", "small.toml", "--out", disk / "out", cwd=tmp_path)  # figures: too big
        assert code == 1 and len(err) == 1, err  # one line (stderr is not a terminal: no progress)
        assert err[0].startswith("error: cannot write") and "No space left" in err[0], err
        assert "previous results left untouched" in err[0]
        assert snapshot(disk / "out") == before and leftovers(disk) == []
    finally:
        subprocess.run(["umount", str(disk)])


def test_read_only_file_system_is_refused_before_compiling(tmp_path, capsys):
    ro = tmp_path / "ro"
    _mount_tmpfs(ro, "ro,size=64k")
    try:
        (tmp_path / "small.toml").write_text(SMALL)
        refused(capsys, "run", "small.toml", "--out", ro / "out", cwd=tmp_path, expect=("Read-only file system",))
    finally:
        subprocess.run(["umount", str(ro)])


def _command():
    script = Path(sys.executable).parent / "tracklab"
    return [str(script)] if script.is_file() else [sys.executable, "-m", "tracklab.cli"]


@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGINT], ids=["kill-9", "ctrl-c"])
def test_a_signal_while_writing_leaves_old_or_complete_new_results(tmp_path, sig):
    """Killed or interrupted while the figures are being written: the folder holds the previous
    results or the complete new ones, never a mix, never nothing; Ctrl-C exits 130."""
    (tmp_path / "small.toml").write_text(SMALL)
    out = tmp_path / "out"
    make_results(out, "previous")
    before = snapshot(out)
    proc = subprocess.Popen([*_command(), "run", "small.toml", "--out", "out"], cwd=tmp_path, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))

    def writing():
        return any((t / "stats.json").exists() for t in tmp_path.glob(f".out.tmp-{proc.pid}-*"))

    try:
        deadline = time.monotonic() + 240
        while not writing() and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.005)  # the write phase has begun: the figures follow
        assert proc.poll() is None, "the run ended before its write phase was seen"
        proc.send_signal(sig)
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    now = snapshot(out)
    complete = {"stats.json", "table.md", "table.csv", "rmse.png", "nees.png", "pred_error.png"} <= set(now)
    assert now == before or complete, sorted(now)
    if sig == signal.SIGINT:
        assert proc.returncode == 130, err
        assert "Traceback" not in err and "interrupted" in err
        assert leftovers(tmp_path) == []
    else:
        assert proc.returncode == -signal.SIGKILL
        clean_stale(out)  # what the next run does first
        assert leftovers(tmp_path) == []
        assert snapshot(out) == now


def _loaded(pid: int, library: str) -> bool:
    """Whether the process has mapped a shared library (Linux), e.g. NumPy's, which only JAX's
    import, inside the command's main, loads."""
    try:
        return library in Path(f"/proc/{pid}/maps").read_text()
    except OSError:
        return False


def test_ctrl_c_at_any_moment_is_one_line_and_exit_130(tmp_path):
    """Ctrl-C while JAX is being imported, 0.5 s and 2 s after the start, and once the program is
    compiled (the runs and the figures under way), through python -m tracklab.cli and the console
    script: exit 130, at most a progress line and the interrupted line on stderr, never a
    traceback, and the results folder neither created nor replaced. (Not before the command's
    own code runs: during the interpreter's start, site and runpy, Python's handler is in place.)"""
    (tmp_path / "small.toml").write_text(SMALL)
    make_results(tmp_path / "old", "previous")
    before = snapshot(tmp_path / "old")
    entries = [[sys.executable, "-m", "tracklab.cli"], _command()]
    runs = []
    for i, when in enumerate(["importing", 0.5, 2.0, "compiled"]):
        env = {k: v for k, v in os.environ.items() if k != "JAX_COMPILATION_CACHE_DIR"}
        env["TRACKLAB_CACHE_DIR"] = str(tmp_path / f"cache{i}")  # empty: compiling takes seconds
        out = "old" if i % 2 else f"new{i}"
        proc = subprocess.Popen([*entries[i % 2], "run", "small.toml", "--runs", "8", "--out", out], cwd=tmp_path,
                                env=env, text=True, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
        runs.append(SimpleNamespace(proc=proc, when=when, out=out, cache=tmp_path / f"cache{i}",
                                    start=time.monotonic(), importing=False, sent=None))
    linux = Path("/proc/self/maps").exists()
    try:
        deadline = time.monotonic() + 240
        while any(r.sent is None and r.proc.poll() is None for r in runs) and time.monotonic() < deadline:
            for r in runs:
                if r.sent is not None or r.proc.poll() is not None:
                    continue
                now = time.monotonic() - r.start
                r.importing = r.importing or (_loaded(r.proc.pid, "_multiarray_umath") if linux else now > 0.3)
                if r.when == "compiled":
                    due = any((r.cache / "programs").glob("*.program"))
                else:  # never before the command's own code runs
                    due = r.importing and (r.when == "importing" or now >= r.when)
                if due:
                    r.proc.send_signal(signal.SIGINT)
                    r.sent = now
            time.sleep(0.002)
        for r in runs:
            _, r.err = r.proc.communicate(timeout=120)
    finally:
        for r in runs:
            if r.proc.poll() is None:
                r.proc.kill()
                r.proc.communicate()
    for r in runs:
        what = (r.when, r.sent, r.err)
        assert r.sent is not None, f"{r.when}: the run ended first (exit {r.proc.returncode}): {r.err}"
        lines = r.err.strip().splitlines()
        assert r.proc.returncode == 130, what
        assert "Traceback" not in r.err and len(lines) <= 2 and lines[-1].startswith("interrupted:"), what
        if r.out == "old":
            assert snapshot(tmp_path / "old") == before, what
        else:
            assert not (tmp_path / r.out).exists(), what
    assert leftovers(tmp_path) == []


@pytest.mark.parametrize("when", ["none", "in an exit function", "held back"])
def test_a_ctrl_c_while_the_command_exits_makes_it_exit_130(when):
    """A SIGINT that comes once the work is done, while the command's process exits (its exit
    functions, JAX's among them, or held back by a blocked mask), still ends it with one line
    and exit 130; without one the process exits with the command's status."""
    probe = f"""
import atexit, os, signal
from tracklab import cli, interrupts
signal.signal(signal.SIGINT, signal.SIG_DFL)  # as a terminal starts the command
interrupts.catch_interrupts()
print("results written", flush=True)
if {when!r} == "in an exit function":
    atexit.register(os.kill, os.getpid(), signal.SIGINT)
elif {when!r} == "held back":
    signal.pthread_sigmask(signal.SIG_BLOCK, {{signal.SIGINT}})
    os.kill(os.getpid(), signal.SIGINT)
cli._end(3)
"""
    r = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=60)
    assert r.stdout == "results written\n"
    if when == "none":
        assert (r.returncode, r.stderr) == (3, "")
    else:
        assert (r.returncode, r.stderr) == (130, "interrupted: previous results left untouched\n")


# --- missing statistics are missing, never 0 or nan -----------------------------------------------


def test_airborne_tracker_that_lost_lock_everywhere_shows_missing(tmp_path):
    from tracklab.report.airborne import airborne_tables, write_airborne_results

    p = tmp_path / "air.toml"
    p.write_text(AIRBORNE.replace("duration = 4.0", "duration = 25.0") + '\n[[tracker]]\nkind = "classical"\n')
    exp = load_experiment(p)
    T = exp.steps
    lost = {"n": np.zeros(T), "sum_e": np.zeros((T, 9)), "sum_e2": np.zeros((T, 9)), "sum_point2": np.zeros(T),
            "sum_nees": np.zeros(T), "n_nees": np.zeros(T), "lost": 4.0}
    fine = {"n": np.full(T, 4.0), "sum_e": np.ones((T, 9)), "sum_e2": np.full((T, 9), 4e-6),
            "sum_point2": np.full(T, 4e-6), "sum_nees": np.full(T, 36.0), "n_nees": np.full(T, 4.0), "lost": 0.0}
    doc = exp.document({"cd_ekf": lost, "classical": fine}, 4, 1.0, 0.5, "float64")
    s = doc["filters"]["cd_ekf"]["summary"]
    assert s["lost_lock"] == 4 and s["healthy_runs"] == 0
    for key in ("rmse_pos", "rmse_vel", "pointing[steady]", "range[steady]"):
        assert np.isnan(s[key]), key
    assert not any(k.startswith("settle[") for k in s)  # no settling time of a lost track
    assert doc["filters"]["classical"]["summary"]["rmse_pos"] == pytest.approx(1.0)  # 1 mrad
    table = airborne_tables(doc)
    row = next(line for line in table.splitlines() if line.startswith("| cd_ekf | cd_ekf |"))
    assert "0.000" not in row and "—" in row
    assert "| cd_ekf | — | 4 |" in table  # settling missing, lost lock counted
    write_airborne_results(doc, tmp_path, figures=True)
    stats = json.loads((tmp_path / "stats.json").read_text())
    assert stats["filters"]["cd_ekf"]["summary"]["rmse_pos"] is None
    assert stats["filters"]["cd_ekf"]["summary"]["lost_lock"] == 4
    assert "0.00" not in (tmp_path / "table.csv").read_text().splitlines()[1]


def _merged(parts):
    added, largest = parts  # what adds up over runs, and what is the largest
    return added | largest


def test_servo_case_statistics_leave_diverged_runs_out():
    from tracklab.worlds.servo.statistics import case_summary
    from tracklab.worlds.servo.world import case_sums

    mx = np.array([0.1, 0.2, np.inf, 1e20, 0.05])  # deg: two healthy runs, one overflowed, one lost the target
    rnd = np.array([0.001, 0.003, np.nan, 1e19, 0.002])
    live = np.array([True, True, True, True, False])  # the last run is padding
    s = case_summary(_merged(case_sums(mx, rnd, np.array([0.5, 0.7, 1.0, 1.0, 9.0]), live)), 4, True)
    assert s["diverged"] == 2 and s["runs"] == 4
    assert s["max_track_err"] == pytest.approx(0.15 * 60) and s["max_track_err_worst"] == pytest.approx(0.2 * 60)
    assert s["random_err"] == pytest.approx(0.002 * 3600) and s["max_rate_err"] == pytest.approx(0.6)
    none = case_summary(_merged(case_sums(np.array([np.nan, 400.0]), np.array([1.0, 1.0]), None, np.ones(2, bool))), 2, False)
    assert none["diverged"] == 2 and all(np.isnan(none[k]) for k in ("max_track_err", "random_err", "max_rate_err"))


def test_sweep_table_shows_missing_not_nan(tmp_path):
    from tracklab.report.sweep import write_sweep

    summary = lambda v: {"rmse_pos": v, "rmse_vel": v, "pred_err_rms": v, "nees": v, "nees_in_bounds": v,
                         "diverged": 0 if np.isfinite(v) else 6}
    points = [{"values": {"q": f}, "stats": {"filters": {"KF": {"kind": "kf", "summary": summary(v)}}}}
              for f, v in ((0.5, 3.0), (2.0, float("nan")))]
    exp = SimpleNamespace(name="s", window=(1, 6), raw={}, path=tmp_path / "s.toml")
    write_sweep(exp, {"axes": {"q": [0.5, 2.0]}, "titles": {"q": "q scale factor"}, "log": {"q": True},
                      "metrics": [["rmse_pos", "position RMSE (m)"]], "points": points, "wall_s": 1.0,
                      "compile_s": 0.5, "runs": 6, "units": ["m"]}, tmp_path / "sw", figures=True)
    md = (tmp_path / "sw" / "table.md").read_text()
    assert "nan" not in md.lower() and "| 2 | KF | — | — | — | — | — | 6 |" in md
    assert "nan" not in (tmp_path / "sw" / "table.csv").read_text().lower()
    assert (tmp_path / "sw" / "sweep_rmse_pos.png").is_file()
    assert listed(tmp_path / "sw") == sorted(set(os.listdir(tmp_path / "sw")) - {MANIFEST})  # the figures too
    doc = json.loads((tmp_path / "sw" / "sweep.json").read_text())
    assert doc[HEADER_KEY] and doc["points"][1]["filters"]["KF"]["summary"]["rmse_pos"] is None


def test_tune_writes_its_results_folder_again_and_keeps_a_users_file_in_it(tmp_path, capsys):
    """A tuning's results folder (tune.json, tune.log, table.md, loss.png) is one tracklab wrote:
    the same command again replaces it; with a file of the user's added, it is refused."""
    (tmp_path / "small.toml").write_text(SMALL)
    args = ("tune", "small.toml", "--params", "q", "--steps", "1", "--runs-per-step", "4", "--out", "t.toml",
            "--results", "rep")
    for _ in range(2):
        code, out, err = main(capsys, *args, cwd=tmp_path)
        assert code == 0, err
    assert sorted(os.listdir(tmp_path / "rep")) == [MANIFEST, "loss.png", "table.md", "tune.json", "tune.log"]
    (tmp_path / "rep" / "notes.txt").write_text("precious")
    code, out, err = main(capsys, *args, cwd=tmp_path)
    assert code == 2 and "tracklab did not write" in err[-1] and "notes.txt" in err[-1], err
    assert (tmp_path / "rep" / "notes.txt").read_text() == "precious"


def test_tune_that_blows_up_writes_the_last_finite_parameters(tmp_path, capsys):
    (tmp_path / "small.toml").write_text(SMALL)
    code, out, err = main(capsys, "tune", "small.toml", "--params", "q,r", "--lr", "1e300", "--steps", "3",
                          "--runs-per-step", "4", "--out", "t.toml", cwd=tmp_path)
    assert code == 0, err
    assert any("stopped" in line and "step 0" in line for line in err), err
    assert "stopped" in out and "inf" not in out.lower() and "nan" not in out.lower()
    tuned = load_experiment(tmp_path / "t.toml")  # one that `tracklab run` accepts
    assert tuned.filters[0].params["q"] == pytest.approx(1.0)  # the last finite parameters: the start
    assert check_tuned_file(tmp_path / "t.toml", tmp_path / "small.toml")  # a file tune wrote may be replaced


# --- the same validation everywhere --------------------------------------------------------------


@pytest.mark.parametrize("text, field, expect", [
    (SMALL.replace("sigma = 10.0", "sigma = 10.0\nperiod = 1e-7"), "sensor.period", "whole multiple"),
    (SMALL.replace("sigma = 10.0", "sigma = 10.0\nperiod = 1e-300"), "sensor.period", "whole multiple"),
    (SMALL.replace("sigma = 10.0", "sigma = 10.0\noffset = 1e-7"), "sensor.offset", "whole multiple"),
    (SMALL.replace("sigma = 10.0", "sigma = 10.0\noffset = 100.0"), "sensor.offset", "reports at no step"),
    (SMALL.replace('label = "KF"', 'label = "   "'), "filter[1].label", "only spaces"),
    (AIRBORNE.replace('kind = "cd_ekf"', 'kind = "cd_ekf"\nlabel = ""'), "tracker[1].label", "only spaces"),
    (AIRBORNE.replace('kind = "cd_ekf"', 'kind = "cd_ekf"\nlabel = " \\t"'), "tracker[1].label", "one line"),
    (SERVO.replace('mode = "double_loop"', 'mode = "double_loop"\nlabel = "  "'), "case[1].label", "only spaces"),
    (SERVO + '\n[[estimator]]\nkind = "kf"\nlabel = ""\n', "estimator[1].label", "only spaces"),
    (SERVO.replace("settle = 0.5", "settle = 0.5\ndelay = 100"), "servo.delay", "fewer frames"),
    (SERVO.replace("settle = 0.5", "settle = 0.5\ndelay = 6"), "servo.delay", "delay margin"),
    (SERVO.replace("settle = 0.5", "settle = 0.5\nframe_dt = 1.0"), "servo.frame_ticks", "tick"),
    (SERVO.replace("frames = 100", "frames = 10000000").replace("settle = 0.5", "settle = 0.5\nframe_ticks = 1000\nframe_dt = 1.0"),
     "servo.frames", "servo ticks"),
    (SERVO.replace("runs = 2", "runs = 100000000").replace("frames = 100", "frames = 1000000"), "experiment.runs",
     "servo ticks"),
    (AIRBORNE.replace("duration = 4.0", "duration = 4.0\nsample_dt = 1e-9"), "airborne.sample_dt", "radar samples"),
    (AIRBORNE.replace("duration = 4.0", "duration = 4.0\nsample_dt = 1e-7"), "airborne.sample_dt", "radar samples"),
    ("[experiment]\nname = 'x'\ndescription = " + "[" * 3000 + "]" * 3000 + "\n", "file", "nested too deeply"),
    (SMALL.replace('kind = "constant_velocity"', 'kind = "trajectory"\npath = "loop.csv"'), "scenario.path", "cannot be opened"),
])
def test_bad_values_refused_in_one_line(tmp_path, text, field, expect):
    (tmp_path / "loop.csv").symlink_to(tmp_path / "loop.csv")
    p = tmp_path / "bad.toml"
    p.write_text(text)
    with pytest.raises(ConfigError) as info:
        load_experiment(p)
    msg = str(info.value)
    assert "\n" not in msg and info.value.field == field and expect in msg, msg


def test_servo_latency_inside_the_margin_and_on_axis_are_accepted(tmp_path):
    p = tmp_path / "ok.toml"
    p.write_text(SERVO.replace("settle = 0.5", "settle = 0.5\ndelay = 5"))  # 55 ms < 57 ms
    assert load_experiment(p).delay == 5
    p.write_text(SERVO.replace("settle = 0.5", "settle = 0.5\ndelay = 9").replace(
        'mode = "double_loop"', 'mode = "on_axis"\nestimator = "perfect"'))  # predicts ahead: no such limit
    assert load_experiment(p).delay == 9


@pytest.mark.parametrize("args, expect", [
    (("sweep", "air.toml", "--grid", "lam=1:2:2"), "no filter of this experiment declares a scalable parameter 'lam'"),
    (("tune", "air.toml", "--params", "q"), "must name parameters among q_scale, r_scale, lam"),
    (("tune", "air.toml", "--params", "lam", "--loss", "mse_pos"), "must be one of pointing, los_rate"),
    (("sweep", "servo.toml", "--grid", "experiment.runs=2:4:2", "--runs", "3"), "give one of them"),
    (("sweep", "servo.toml", "--grid", "q=1:2:2"), "no filter of this experiment declares a scalable parameter 'q'"),
    (("tune", "servo.toml", "--params", "q"), "no filter here declares a tunable number"),
    (("sweep", "small.toml", "--grid", "rho=0.5:1:2"), "no filter of this experiment declares a scalable parameter 'rho'"),
    (("tune", "small.toml", "--params", "rho"), "must name parameters among q, r"),
    (("tune", "small.toml", "--params", "q", "--filters", "nope"), "--filters"),
    (("tune", "two.toml", "--params", "r", "--filters", "KF"), "several sensors"),
    (("run", "small.toml", "--max-memory", "2K"), "more than --max-memory"),
    (("tune", "small.toml", "--params", "q", "--runs-per-step", "10000000000"), "fewer --runs-per-step"),
    (("sweep", "two.toml", "--grid", "q=0.1:10:1000", "--grid", "r=0.1:10:1000", "--grid", "rho=0.5:1:1000"),
     "fewer grid points"),
    (("run", "big.toml"), "experiment.chunk"),
    (("table", "bad1"), "'filters'"),
    (("table", "bad2"), "'filters'"),
    (("table", "bad3"), "'summary'"),
    (("table", "bad4"), "JSON"),
    (("table", "nowhere"), "missing"),
    (("table", "bad5"), "summary.rmse_pos"),
    (("list", "--dir", "nowhere"), "must be a folder"),
    (("run", "small.toml", "--out", "loopa/x"), "symbolic link to nothing (or a loop)"),
    (("run", "small.toml", "--out", "/".join(["d" * 200] * 25)), "longer than this system's"),
    (("run", "small.toml", "--runs", "-3"), "must be >= 1"),
    (("sweep", "small.toml"), "--grid"),
    (("reproduce", "--experiments", "/nonexistent"), "must be a folder"),
    (("reproduce", "--experiments", "empty"), "no experiment file"),
])
def test_commands_refuse_in_one_line_before_compiling(tmp_path, capsys, args, expect):
    for name, text in (("small.toml", SMALL), ("two.toml", TWO_SENSORS), ("air.toml", AIRBORNE), ("servo.toml", SERVO),
                       ("big.toml", SMALL.replace("steps = 6", "steps = 100000\nchunk = 1000000").replace(
                           "runs = 6", "runs = 1000000"))):
        (tmp_path / name).write_text(text)
    for name, text in (("bad1", "[]"), ("bad2", '{"filters": 5}'), ("bad3", '{"filters": {"KF": {"kind": "kf"}}}'),
                       ("bad4", "[" * 100_000), ("bad5", '{"filters": {"KF": {"summary": {"rmse_pos": 1%s}}}}' % ("0" * 400))):
        (tmp_path / name).mkdir()
        (tmp_path / name / "stats.json").write_text(text)
    (tmp_path / "empty").mkdir()
    (tmp_path / "loopa").symlink_to(tmp_path / "loopb")
    (tmp_path / "loopb").symlink_to(tmp_path / "loopa")
    before = snapshot(tmp_path)
    refused(capsys, *args, cwd=tmp_path, expect=(expect,))
    assert snapshot(tmp_path) == before


def test_reproduce_refuses_a_readme_it_did_not_write_and_a_study_grid_no_filter_has(tmp_path, capsys):
    exps = tmp_path / "exps"
    exps.mkdir()
    (exps / "small.toml").write_text(SMALL)
    (tmp_path / "res").mkdir()
    (tmp_path / "res" / "README.md").write_text("# my own notes\n")
    before = snapshot(tmp_path)
    refused(capsys, "reproduce", "--experiments", "exps", "--out", "res", cwd=tmp_path, expect=("did not write",))
    for out, expect in ((".", "working folder"), ("exps", "experiment files")):
        refused(capsys, "reproduce", "--experiments", "exps", "--out", out, cwd=tmp_path, expect=(expect,))
    assert snapshot(tmp_path) == before
    (exps / "small.toml").write_text(SMALL + '\n[[study]]\nkind = "sweep"\ngrid = ["rho=0.5:1:2"]\nout = "s"\n')
    refused(capsys, "reproduce", "--experiments", "exps", "--out", "res2", cwd=tmp_path,
            expect=("study[1].grid", "no filter of this experiment has the parameter 'rho'"))
    assert not (tmp_path / "res2").exists()


def test_heatmap_cells_are_centred_on_their_grid_values():
    from tracklab.report.sweep import _log_edges

    edges = _log_edges([0.1, 1.0, 10.0])
    np.testing.assert_allclose(edges, [10**-1.5, 10**-0.5, 10**0.5, 10**1.5])
    centres = np.sqrt(edges[1:] * edges[:-1])  # on a log axis
    np.testing.assert_allclose(centres, [0.1, 1.0, 10.0])
    np.testing.assert_allclose(_log_edges([3.0]), [1.5, 6.0])


def test_a_label_cannot_break_a_markdown_table(tmp_path):
    from tracklab.report.airborne import airborne_tables
    from tracklab.report.tables import markdown_table

    doc = {"filters": {"EKF | x": {"kind": "ekf", "summary": {"rmse_pos": 1.0, "runs": 3}}}}
    row = markdown_table(doc).splitlines()[2]
    assert row == "| EKF \\| x | ekf | 1.00 | 3 |"
    air = {"name": "a", "runs": 2, "steps": 3, "dt": 0.05, "windows": ["acquisition"],
           "filters": {"EKF | x": {"kind": "cd_ekf", "summary": {"lost_lock": 0}}}}
    table = airborne_tables(air)  # no steady window: no settling columns, a well-formed table
    assert "| tracker | lost lock (runs) |\n|---|---|\n| EKF \\| x | 0 |" in table
