"""A filter of one's own whose factory declares its numbers (``tracklab.declare``) goes where a
built-in kind goes: ``tracklab run`` beside a built-in, ``tracklab tune --params`` on its own
numbers (the tuned file, written under results/, runs), ``tracklab sweep`` over its numbers and
over the sensor's in one program, and an edit of a declared number reruns without compiling."""

import json
import textwrap

import numpy as np
import pytest

from tracklab.cli import main
from tracklab.report.document import read_results
from tracklab.config import load_experiment
from tracklab.montecarlo import programs, runner

SINGER = '''
"""A Singer-model EKF for a 2-D range-bearing radar (Singer, IEEE Trans. AES 1970)."""
import jax
import jax.numpy as jnp

import tracklab
from tracklab import Layout, Param
from tracklab.filters import ekf_update, kalman_filter, predict


def blocks(T, tau, sigma_m):
    """F and Q of one axis [x, v, a] over T (Van Loan): acceleration a first-order Markov process."""
    A = jnp.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [0.0, 0.0, 0.0]]).at[2, 2].set(-1.0 / tau)
    Qc = jnp.zeros((3, 3)).at[2, 2].set(2.0 * sigma_m**2 / tau)
    E = jax.scipy.linalg.expm(jnp.block([[-A, Qc], [jnp.zeros((3, 3)), A.T]]) * T)
    F = E[3:, 3:].T
    return F, F @ E[:3, 3:]


@tracklab.declare(
    tau=Param(doc="manoeuvre time constant", unit="s", default=20.0, constraint="positive"),
    sigma_m=Param(doc="RMS manoeuvre acceleration", unit="m/s²", default=5.0, constraint="positive"),
    r=Param(doc="range and bearing noise variances", unit="m², rad²", constraint="positive",
            default=lambda context: jnp.diag(jnp.asarray(context.R))))
def singer(context):
    T = context.dt
    h = lambda x: jnp.stack([jnp.hypot(x[0], x[3]), jnp.arctan2(x[3], x[0])])

    def time_update(params, g):
        F, Q = blocks(T, params["tau"], params["sigma_m"])
        return predict(g, jax.scipy.linalg.block_diag(F, F), jax.scipy.linalg.block_diag(Q, Q))

    def measurement_update(params, g, z, present):
        return ekf_update(g, z, h, jnp.diag(params["r"]), angles=(False, True), present=present)

    return kalman_filter({}, time_update, measurement_update, layout=Layout(n=6, pos_idx=(0, 3), vel_idx=(1, 4)))
'''

EXPERIMENT = """
[experiment]
name = "singer"
runs = 64
dt = 1.0
steps = 40

[scenario]
kind = "manoeuvre"
initial = [-8000.0, 250.0, 12000.0, 0.0]
segments = [{duration = 15.0}, {duration = 10.0, turn_g = 4.0}, {duration = 15.0}]

[sensor]
kind = "polar"
sigma_r = 30.0
sigma_angle = 0.002

[prior]
acc_sigma = 5.0

[[filter]]
kind = "ekf"
label = "EKF"
accel_sigma = 15.0

[[filter]]
kind = "singer:singer"
label = "Singer"
tau = 10.0          # s
sigma_m = 8.0       # m/s^2
"""


@pytest.fixture
def folder(tmp_path, monkeypatch):
    (tmp_path / "exp").mkdir()
    (tmp_path / "exp" / "singer.py").write_text(SINGER)
    (tmp_path / "exp" / "singer.toml").write_text(textwrap.dedent(EXPERIMENT))
    monkeypatch.chdir(tmp_path)  # results/ here
    return tmp_path


def test_a_declared_filter_is_run_tuned_and_swept_from_the_command_line(folder, capsys):
    path = folder / "exp" / "singer.toml"
    session = programs.folder()
    programs.keep_in(folder / "programs")  # a store of its own: the first run is cold
    try:
        assert main(["run", str(path), "--no-figures", "--out", "results/cold"]) == 0
        cold = read_results(folder / "results" / "cold")
        assert cold["filters"]["Singer"]["params"]["tau"] == 10.0 and cold["filters"]["Singer"]["summary"]["diverged"] == 0
        path.write_text(path.read_text().replace("tau = 10.0", "tau = 14.0"))  # an edit of a declared number
        runner._PROGRAMS.clear()  # as a new process: the program is found in the store, not compiled
        loaded = programs.loaded
        assert main(["run", str(path), "--no-figures", "--out", "results/warm"]) == 0
        warm = read_results(folder / "results" / "warm")
        assert programs.loaded == loaded + 1 and warm["compile_s"] <= 0.4 * cold["compile_s"], (warm["compile_s"], cold["compile_s"])
        assert warm["filters"]["Singer"]["summary"]["rmse_pos"] != cold["filters"]["Singer"]["summary"]["rmse_pos"]
    finally:
        programs.keep_in(session)
    capsys.readouterr()

    assert main(["tune", str(path), "--params", "tau,sigma_m", "--steps", "2", "--runs-per-step", "8",
                 "--no-figures"]) == 0
    tuned_file = folder / "results" / "singer_tuned.toml"
    text = tuned_file.read_text()
    assert "tau = 14.0" not in text and "# s" in text and 'pythonpath = ["../exp"]' in text, text
    tuned = load_experiment(tuned_file)
    assert [f.label for f in tuned.filters] == ["EKF", "Singer, tuned"]
    assert main(["run", str(tuned_file), "--runs", "64", "--no-figures"]) == 0  # the file's count: its program again
    out = capsys.readouterr().out
    assert any(line.startswith("Singer, tuned ") for line in out.splitlines()), out  # its row of the printed table

    # its declared number, the sensor's and a scale factor of its numbers: three axes, one program
    grids = ("filter[Singer].tau=5:20:2", "sensor.sigma_r=20:40:2", "sigma_m=0.5:2:2")
    assert main(["sweep", str(path), *(a for g in grids for a in ("--grid", g)), "--runs", "16", "--no-figures",
                 "--out", "results/sw"]) == 0
    assert "programs" not in capsys.readouterr().err  # one program: no line about several
    doc = json.loads((folder / "results" / "sw" / "sweep.json").read_text())
    points = [(p["values"], p["filters"]["Singer"]["summary"]["rmse_pos"]) for p in doc["points"]]
    assert len(points) == 8 and np.all(np.isfinite([r for _, r in points]))
    for axis in points[0][0]:  # each axis alone changes what runs
        pairs = [(r1, r2) for v1, r1 in points for v2, r2 in points
                 if v1[axis] < v2[axis] and all(v1[k] == v2[k] for k in v1 if k != axis)]
        assert len(pairs) == 4 and all(r1 != r2 for r1, r2 in pairs), axis


def test_a_declared_number_is_checked_against_its_declaration(folder, capsys):
    path = folder / "exp" / "singer.toml"
    for bad, field in (("tau = -1.0", "filter[2].tau"), ('tau = "ten"', "filter[2].tau")):
        path.write_text(textwrap.dedent(EXPERIMENT).replace("tau = 10.0", bad))
        assert main(["run", str(path), "--out", "results/x"]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and field in err[0], err
