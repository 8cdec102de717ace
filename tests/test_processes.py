"""Several processes (jax.distributed): two processes on this machine, exchanging their sums
over localhost, give the statistics of one process in chunks of another size (trackers in
clutter: every sum, the track losses, by error and by existence, and their paired differences
among them); only process 0 writes and prints."""

import os
import re
import socket
import subprocess
import time

import numpy as np
import pytest

from tracklab import processes
from tracklab.config import load_experiment
from tracklab.report.document import read_results

from test_cli import _command
from test_clutter import CLUTTER_IPDA

EXPERIMENT = CLUTTER_IPDA.replace('name = "clutter_small"', 'name = "two_processes"').replace("runs = 128", "runs = 50")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _wait_connected(port: int, timeout: float):
    """Until a TCP connection to ``port`` on this machine is established (Linux's /proc/net)."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        for table in ("/proc/net/tcp", "/proc/net/tcp6"):
            try:
                rows = open(table).read().splitlines()[1:]
            except OSError:
                continue
            if any(r.split()[2].endswith(f":{port:04X}") and r.split()[3] == "01" for r in rows):
                return
        time.sleep(0.2)


def _numbers(a, b, where):
    """Every number of ``a`` equals ``b``'s to 1e-12 (relative): the chunk-size tests' tolerance (a
    series.npz array: to its single-precision rounding); in a series, relative to its largest entry (a mean error near zero at one step is a difference of
    sums whose rounding is that of the sums)."""
    if isinstance(a, np.ndarray):  # a series of series.npz, stored in single precision: to its rounding
        assert isinstance(b, np.ndarray) and a.shape == b.shape, where
        scale = float(np.nanmax(np.abs(a))) if np.isfinite(a).any() else 0.0
        np.testing.assert_allclose(b, a, rtol=2e-7, atol=2e-7 * scale + 1e-300, err_msg=where)
    elif isinstance(a, list) and a and all(isinstance(x, float) for x in a):
        assert len(a) == len(b), where
        scale = float(np.nanmax(np.abs(a))) if np.any(np.isfinite(a)) else 0.0
        np.testing.assert_allclose(b, a, rtol=1e-12, atol=1e-12 * scale + 1e-300, err_msg=where)
    elif isinstance(a, dict):
        assert set(a) == set(b), where
        for k in a:
            _numbers(a[k], b[k], f"{where}.{k}")
    elif isinstance(a, list):
        assert len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b)):
            _numbers(x, y, f"{where}[{i}]")
    elif isinstance(a, float) and isinstance(b, (int, float)):
        np.testing.assert_allclose(b, a, rtol=1e-12, atol=1e-300, err_msg=where)
    else:
        assert a == b, where


def test_two_processes_give_the_statistics_of_one(tmp_path, xla_flags):
    path = tmp_path / "exp.toml"
    path.write_text(EXPERIMENT)
    env = dict(os.environ, XLA_FLAGS=xla_flags(1))
    run = [*_command(), "run", str(path), "--no-figures"]
    coordinator = f"127.0.0.1:{_free_port()}"
    # process 0 from the options, process 1 from the environment
    procs = [subprocess.Popen(run + ["--out", str(tmp_path / "two"), "--coordinator", coordinator, "--processes", "2",
                                     "--process-id", "0"], env=env, text=True, stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE),
             subprocess.Popen(run + ["--out", str(tmp_path / "two")], text=True, stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE,
                              env=dict(env, TRACKLAB_COORDINATOR=coordinator, TRACKLAB_PROCESSES="2",
                                       TRACKLAB_PROCESS_ID="1"))]
    outs = [p.communicate(timeout=600) for p in procs]
    assert [p.returncode for p in procs] == [0, 0], outs
    # process 0 alone prints (the collectives' library may announce its connection in both)
    assert "results written to" in outs[0][0] and "written" not in outs[1][0] and "RMSE" not in outs[1][0]
    one = load_experiment(path)
    one.chunk = 16  # one process (this one, with the same flags) in chunks of another size
    one.run(out=tmp_path / "one", figures=False)
    a = read_results(tmp_path / "one")
    b = read_results(tmp_path / "two")
    assert a["runs"] == b["runs"] == 50
    for label in a["filters"]:
        for part in ("summary", "half_width", "intervals", "paired", "cdf", "series"):
            _numbers(a["filters"][label][part], b["filters"][label][part], f"{label}.{part}")
    _numbers(a["overflow"], b["overflow"], "overflow")
    assert a["filters"]["IPDA"]["summary"]["lost"] > 0  # the losses were counted, not all zero
    assert sorted(p.name for p in tmp_path.iterdir()) == ["exp.toml", "one", "two"]  # nothing else written


def test_a_partial_process_setting_is_refused_in_one_line(tmp_path):
    path = tmp_path / "exp.toml"
    path.write_text(EXPERIMENT)
    r = subprocess.run([*_command(), "run", str(path), "--processes", "2"], text=True, capture_output=True,
                       timeout=120, env=dict(os.environ, TRACKLAB_COORDINATOR="", TRACKLAB_PROCESS_ID=""))
    assert r.returncode == 2
    assert r.stderr.count("\n") == 1 and "coordinator" in r.stderr
    assert not (tmp_path / "results").exists()


@pytest.mark.parametrize("kwargs, says", [
    (dict(coordinator="localhost:99999", processes=2, process_id=0), "not in 1–65535"),
    (dict(coordinator="localhost:notaport", processes=2, process_id=0), "is not a number"),
    (dict(coordinator="localhost", processes=2, process_id=0), "HOST:PORT"),
    (dict(coordinator="no-such-host.invalid:7777", processes=2, process_id=0), "cannot be resolved"),
    (dict(coordinator="localhost:7777", processes=1, process_id=5), "must be in 0 … 0"),
    (dict(coordinator="localhost:7777", processes=2, process_id=2), "must be in 0 … 1"),
    (dict(coordinator="localhost:7777", processes=2, process_id=-1), "at least 0"),
    (dict(coordinator="localhost:7777", processes=0, process_id=0), "at least 1"),
    (dict(coordinator="localhost:7777", processes=2, process_id=1, timeout=0), "must be positive"),
    (dict(processes=2, process_id=1), "the coordinator address (--coordinator) is missing"),
])
def test_process_settings_are_checked_before_anything_starts(kwargs, says, monkeypatch):
    for name in processes.ENV.values():
        monkeypatch.delenv(name, raising=False)
    with pytest.raises(ValueError, match=re.escape(says)) as e:
        processes.settings(**kwargs)
    assert "\n" not in str(e.value)
    assert processes.settings("localhost:7777", 1, 0) is None  # one process: nothing to start
    assert processes.settings("[::1]:7777", 2, 1).coordinator == "[::1]:7777"


def test_processes_that_cannot_meet_or_disagree_stop_in_one_line(tmp_path):
    """Each fault ends every process it reaches with one line, its exit status (2: settings that
    cannot work, 1: a process that failed) and nothing written, within the timeout: a coordinator
    nobody runs, a peer that never comes, two processes given different run counts, and a peer
    killed while process 0 runs. All four start at once."""
    path = tmp_path / "exp.toml"
    path.write_text(EXPERIMENT)
    env = dict(os.environ, **{name: "" for name in processes.ENV.values()})

    def start(port, pid, *extra, timeout=2):
        out = tmp_path / f"out{port}"
        return subprocess.Popen([*_command(), "run", str(path), "--no-figures", "--out", str(out), "--coordinator",
                                 f"127.0.0.1:{port}", "--processes", "2", "--process-id", str(pid),
                                 "--process-timeout", str(timeout), *extra], env=env, text=True,
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE)

    ports = [_free_port() for _ in range(4)]
    t0 = time.monotonic()
    lone_peer = start(ports[0], 1)
    lone_coordinator = start(ports[1], 0)
    disagree = [start(ports[2], 0, "--runs", "100", timeout=30), start(ports[2], 1, "--runs", "300", timeout=30)]
    killed = [start(ports[3], i, "--runs", "50000000", timeout=30) for i in (0, 1)]
    _wait_connected(ports[3], 60)  # the pair has met; whatever process 0 does next, it must stop
    time.sleep(1)
    killed[1].kill()
    results = {name: [(p.wait(timeout=120), *p.communicate()) for p in ps] for name, ps in
               [("lone peer", [lone_peer]), ("lone coordinator", [lone_coordinator]), ("disagree", disagree),
                ("killed", killed[:1])]}
    assert time.monotonic() - t0 < 100
    want = {"lone peer": [(1, "waited 2 s for process 0")], "lone coordinator": [(1, "for process 1 of 2: never connected")],
            "disagree": [(2, "runs (300 there, 100 in process 0) differ")] * 2, "killed": [(1, "process 0 of 2 stops")]}
    for name, outcomes in results.items():
        for (code, out, err), (status, says) in zip(outcomes, want[name]):
            said = says in err or (name == "killed" and "process 1 of 2 ended" in err)  # in an exchange, or between
            assert code == status and said, (name, code, err)
            assert err.count("\n") == 1 and "Traceback" not in err and "@ 0x" not in err, (name, err)
            assert "|" not in out and "RMSE" not in out, (name, out)  # no table printed
    assert not [p for p in tmp_path.iterdir() if p.name != "exp.toml"]  # nothing written, nothing left behind


def _pair(timeout=2.0):
    """Process 0's and process 1's meetings, joined as after the start (no JAX)."""
    a, b = socket.socketpair()
    zero = processes.Meeting(processes.Settings("127.0.0.1", 1, 2, 0, timeout), {1: a})
    one = processes.Meeting(processes.Settings("127.0.0.1", 1, 2, 1, timeout), {0: b})
    for m in (zero, one):
        m.watch()
        m.started.set()
    return zero, one


def _finish_both(zero, one):
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(2) as pool:
        ends = [pool.submit(processes.finish, m) for m in (zero, one)]
        return [e.result(timeout=30) for e in ends]


def test_the_processes_end_together_or_say_who_is_missing():
    """The end of a run of several processes (``processes.finish``), without JAX: both reach
    their end and leave together; a peer that ended after saying it was done leaves process 0's
    results whole (a note, exit 0) and JAX's shutdown barrier, which would wait for it, skipped;
    process 0 gone leaves the peer with one line and exit 1."""
    assert _finish_both(*_pair()) == [None, None]

    zero, one = _pair()
    one.ending.set()  # the peer reaches its end, says it is done, then is gone
    processes._send(one.peers[0], {"done": True})
    one.peers[0].shutdown(socket.SHUT_RDWR)
    time.sleep(0.2)
    status, line = processes.finish(zero)
    assert status == 0 and "process 1 of 2 ended before the end" in line and "complete" in line

    zero, one = _pair()
    one.ending.set()  # the peer waits at its end; process 0 is gone before its own
    zero.ending.set()
    zero.peers[1].shutdown(socket.SHUT_RDWR)
    time.sleep(0.2)
    status, line = processes.finish(one)
    assert status == 1 and line.startswith("error: process 0") and "\n" not in line
