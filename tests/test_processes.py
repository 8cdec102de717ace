"""Several processes (jax.distributed): two processes on this machine, exchanging their sums
over localhost, give the statistics of one process; only process 0 writes and prints."""

import json
import os
import socket
import subprocess

import numpy as np

from tracklab.config import load_experiment

from test_cli import _command
from test_intervals import LINEAR

EXPERIMENT = LINEAR.replace('name = "linear_small"', 'name = "two_processes"').replace("runs = 20", "runs = 50") + """
[[filter]]
kind = "kf"
label = "KF high q"
accel_sigma = 6.0
"""


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _numbers(a, b, where):
    """Every number of ``a`` equals ``b``'s to 1e-12 (relative): the chunk-size tests' tolerance."""
    if isinstance(a, dict):
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
    assert "results written to" in outs[0][0] and "written" not in outs[1][0] and "|" not in outs[1][0]
    load_experiment(path).run(out=tmp_path / "one", figures=False)  # one process: this one, with the same flags
    a = json.loads((tmp_path / "one" / "stats.json").read_text())
    b = json.loads((tmp_path / "two" / "stats.json").read_text())
    assert a["runs"] == b["runs"] == 50
    for label in a["filters"]:
        for part in ("summary", "half_width", "intervals", "paired", "cdf", "series"):
            _numbers(a["filters"][label][part], b["filters"][label][part], f"{label}.{part}")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["exp.toml", "one", "two"]  # nothing else written


def test_a_partial_process_setting_is_refused_in_one_line(tmp_path):
    path = tmp_path / "exp.toml"
    path.write_text(EXPERIMENT)
    r = subprocess.run([*_command(), "run", str(path), "--processes", "2"], text=True, capture_output=True,
                       timeout=120, env=dict(os.environ, TRACKLAB_COORDINATOR="", TRACKLAB_PROCESS_ID=""))
    assert r.returncode == 2
    assert r.stderr.count("\n") == 1 and "coordinator" in r.stderr
    assert not (tmp_path / "results").exists()
