"""The one Monte-Carlo runner: every world's statistics are the same for any chunk size and device
count, numbers are inputs of the compiled program (one compile for many values and run counts)."""

import json
import os
import subprocess
import sys
from pathlib import Path

import jax
import numpy as np
import pytest

from tracklab.config import load_experiment
from tracklab.montecarlo import runner

AIRBORNE = """
[experiment]
name = "airborne_tiny"
runs = 6
seed = 5

[airborne]
duration = 2.0

[[tracker]]
label = "classical"
kind = "classical"
"""

SERVO = """
[experiment]
name = "servo_tiny"
runs = 6
seed = 2

[servo]
frames = 300
settle = 1.0

[target]
kind = "sine"

[[estimator]]
label = "KF"
kind = "kf"

[[case]]
mode = "on_axis"
estimator = "KF"
"""

TRACKING = """
[experiment]
name = "tracking_tiny"
runs = 6
dt = 0.5
steps = 30

[scenario]
kind = "crossing"
speed = 200.0
offset = 3000.0
start_x = -3000.0

[sensor]
kind = "polar"
sigma_r = 50.0
sigma_angle = 0.004

[[filter]]
kind = "ekf"
label = "EKF"
"""


def _write(tmp_path, name, text):
    path = tmp_path / f"{name}.toml"
    path.write_text(text)
    return path


def _outcome(exp, chunk):
    """Any world's runner outcome over the file's runs in chunks of ``chunk``: the protocol's
    structure, params and world, as ``tracklab run`` runs them."""
    from tracklab.montecarlo import runner

    return runner.run(exp.world(exp.structure(chunk, exp.runs)), exp.params(), exp.runs, exp.seed,
                      precision=exp.precision)


def _sums(exp, chunk):
    """Every world's sums over its runs, flattened: name -> array."""
    import jax

    leaves = jax.tree_util.tree_flatten_with_path(_outcome(exp, chunk).sums)[0]
    return {jax.tree_util.keystr(path): np.asarray(v, float) for path, v in leaves}


def _same(got, ref, what):
    assert got.keys() == ref.keys()
    for k in ref:  # equal up to the order of floating-point sums (a wrong run or key is off by far more)
        np.testing.assert_allclose(got[k], ref[k], rtol=1e-9, atol=1e-12, err_msg=f"{what}: {k}")


@pytest.mark.parametrize("world", ["tracking", "airborne", "servo"])
def test_statistics_do_not_depend_on_the_chunk_size(tmp_path, world):
    """One run per chunk, four per chunk (the second padded with two masked runs), all in one: the
    same sums (run i draws from fold_in(key, i)) and, where a world keeps them, the same per-run
    samples behind the intervals."""
    exp = load_experiment(_write(tmp_path, world, {"tracking": TRACKING, "airborne": AIRBORNE, "servo": SERVO}[world]))
    ref = _sums(exp, exp.runs)
    for chunk in (1, 4):
        _same(_sums(exp, chunk), ref, f"chunk {chunk}")
    a, b = _outcome(exp, exp.runs).samples.pair(0, 0), _outcome(exp, 4).samples.pair(0, 0)
    assert a.n == b.n == exp.runs
    np.testing.assert_allclose(b.mean_f, a.mean_f, rtol=1e-10)  # NaN where a tracker has no NEES (classical loops)
    np.testing.assert_allclose(b.cov_ff, a.cov_ff, rtol=1e-9, atol=1e-12 * np.nanmax(np.abs(a.cov_ff)))


DEVICES = """
import json, sys
import tracklab
tracklab.configure()  # as the command does (the device count from XLA_FLAGS)
import jax, numpy as np
sys.path.insert(0, sys.argv[1])
from test_runner import _sums
from tracklab.config import load_experiment
out = {"devices": jax.device_count()}
for path in sys.argv[2:]:
    exp = load_experiment(path)
    out[path] = {k: v.tolist() for k, v in _sums(exp, 3).items()}
from tracklab.montecarlo import runner
ops = ("all-reduce", "all-gather", "reduce-scatter", "all-to-all", "collective-permute")
out["programs"] = len(runner._PROGRAMS)
out["collectives"] = sorted({op for c in runner._PROGRAMS.values() for op in ops if op in c.as_text()})
print(json.dumps(out))
"""


def test_statistics_do_not_depend_on_the_device_count(tmp_path, xla_flags):
    """Every world's chunks split over 2 devices (3 runs a chunk: one device gets a padded, dead
    run) give the sums of one device, with programs that pass nothing between the devices."""
    paths = [_write(tmp_path, n, t) for n, t in (("tracking", TRACKING), ("airborne", AIRBORNE), ("servo", SERVO))]
    env = dict(os.environ, XLA_FLAGS=xla_flags(2))
    script = tmp_path / "devices.py"
    script.write_text(DEVICES)
    done = subprocess.run([sys.executable, str(script), os.path.dirname(__file__), *map(str, paths)], env=env,
                          capture_output=True, text=True, check=True)
    doc = json.loads(done.stdout.strip().splitlines()[-1])
    assert doc["devices"] == 2 and jax.device_count() == 1
    # each device keeps its own sums; the host combines them: no device waits on another inside a
    # program (a loaded machine could otherwise hold one past XLA's rendezvous timeout, a fatal abort)
    assert doc["programs"] >= 3 and doc["collectives"] == []
    for path in paths:
        ref = _sums(load_experiment(path), 3)
        _same({k: np.asarray(v, float) for k, v in doc[str(path)].items()}, ref, f"{path.stem}, 2 devices")


def test_a_sensor_sigma_is_an_input_of_the_program(tmp_path):
    """Two values of sigma_r and two run counts: one compiled program, different statistics, each
    the same as a run of its own with a freshly compiled program."""
    a = load_experiment(_write(tmp_path, "a", TRACKING))
    b = load_experiment(_write(tmp_path, "b", TRACKING.replace("sigma_r = 50.0", "sigma_r = 150.0")))
    assert a.structure() == b.structure()
    before = runner.compiles
    res_a = a.monte_carlo(chunk=4)
    res_b = b.monte_carlo(chunk=4, runs=13)  # another value and another run count
    assert runner.compiles - before <= 1  # the first call compiles (unless an earlier test did), the second never
    assert res_b.compile_s == 0.0
    ka = res_a.sums["EKF"]["sumsq_pos"]
    kb = res_b.sums["EKF"]["sumsq_pos"]
    assert not np.allclose(ka, kb)
    runner._PROGRAMS.clear()  # a run of its own, with a program compiled for it
    alone = b.monte_carlo(chunk=4, runs=13)
    assert alone.compile_s > 0
    for k, v in alone.sums["EKF"].items():
        np.testing.assert_allclose(res_b.sums["EKF"][k], v, rtol=1e-13, atol=1e-12, err_msg=k)


def _every_kind(order):
    filters = {
        "EKF": 'kind = "ekf"',
        "alpha-beta": 'kind = "alpha_beta"\nconversion = "unbiased"\nsigma_w = [50.0, 50.0]',
        "CMKF": 'kind = "cmkf"\ndebias = "unbiased"',
        "UKF": 'kind = "ukf"',
        "IMM": 'kind = "imm"\nq = [1.0, 1.0, 1.0]\nq_turn = 1e-5\np_stay = 0.95\nturn_rate_sigma = 0.05',
        "STF": 'kind = "stf"\nrho = 0.95\nb = 1.0',
        "Polar KF": 'kind = "polar_kf"',
    }
    head = TRACKING.split("[[filter]]")[0].replace('sigma_angle = 0.004', 'sigma_angle = 0.004\np_detect = 0.8')
    return head + "".join(f'\n[[filter]]\nlabel = "{label}"\n{filters[label]}\n' for label in order)


def test_a_filters_statistics_do_not_depend_on_the_program_around_it(tmp_path):
    """Filters whose errors have the same shapes share their error and statistics kernels, and a
    filter alone makes them inside its own step: every arrangement gives each filter the same
    sums (a mixed-up lane is off by far more): all seven kinds, three of them in another order
    (each in another lane, and sharing its kernels with other filters), one alone."""
    from tracklab.worlds.tracking import outcome

    order = ["EKF", "alpha-beta", "CMKF", "UKF", "IMM", "STF", "Polar KF"]
    exp = load_experiment(_write(tmp_path, "kinds", _every_kind(order)))

    def sums(exp):
        out = outcome.run(exp.structure(), exp.params(), exp.runs, exp.seed).sums
        return {f"{lab}/{k}": np.asarray(v, float) for lab, d in out.items() for k, v in d.items()}

    ref = sums(exp)
    assert ref["EKF/diverged"] == 0 and np.ptp(ref["EKF/count_nis"]) > 0  # missed detections reached the runs
    # three filters in another order: a lane mixed up shows here
    moved = ["Polar KF", "EKF", "CMKF"]
    _same(sums(load_experiment(_write(tmp_path, "moved", _every_kind(moved)))),
          {k: v for k, v in ref.items() if k.split("/")[0] in moved}, "another order")
    alone = sums(load_experiment(_write(tmp_path, "alone", _every_kind(["EKF"]))))
    _same(alone, {k: v for k, v in ref.items() if k.startswith("EKF/")}, "alone")


def test_on_an_accelerator_a_default_chunk_fills_a_share_of_its_memory(monkeypatch):
    """Without a chunk in the file, a GPU's chunk is sized from its memory: a power of two per
    device whose per-step arrays fill at most an eighth of it (capped), rounded to the runs asked
    for; on the CPU the cache-sized chunks stay."""
    from tracklab.worlds.tracking.scan import default_chunk

    assert runner.accelerator_memory() is None  # the test machine's CPU
    exp = load_experiment(Path(__file__).resolve().parents[1] / "experiments" / "lidar_crossing.toml")
    devices = jax.device_count()
    per_run = 8 * exp.steps * (2 * exp.scenario.dim + exp.sensor.m)
    cpu = default_chunk(exp.scenario, exp.sensor)
    assert cpu == 1000 * devices and runner.budget_chunk(1e6) == 128 * devices
    for memory in (80 * 2**30, 64 * 2**20):
        monkeypatch.setattr(runner, "accelerator_memory", lambda: memory)
        chunk = default_chunk(exp.scenario, exp.sensor)
        per_device = chunk // devices
        assert chunk % devices == 0 and per_device & (per_device - 1) == 0
        assert per_device * per_run <= memory * runner.ACCELERATOR_SHARE < 2 * per_device * per_run or \
            per_device == runner.ACCELERATOR_RUNS
        assert default_chunk(exp.scenario, exp.sensor, runs=10_000) == min(
            chunk, devices * (1 << (-(-10_000 // devices) - 1).bit_length()))
        closed = runner.budget_chunk(1e6) // devices  # a closed loop's run of a megabyte
        assert closed & (closed - 1) == 0 and closed * 1e6 <= memory * runner.ACCELERATOR_SHARE < 2 * closed * 1e6
        assert runner.budget_chunk(1e6, runs=3) == min(closed * devices, -(-3 // devices) * devices)
    assert per_device == 2**int(np.log2(64 * 2**20 / 8 / per_run))  # the small device: its memory decides
