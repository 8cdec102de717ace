"""Compiled programs kept on disk (``montecarlo.programs``): a new process loads the program
instead of tracing and compiling it, with the same statistics to the last bit; a filter of
one's own is kept by what it compiles to; an unreadable file is compiled again; a program JAX loaded from its
own cache is never kept."""

import json
import os
import subprocess
import sys
from pathlib import Path

import jax
import numpy as np

from tracklab.config import load_experiment
from tracklab.montecarlo import programs

from test_runner import AIRBORNE, SERVO, TRACKING, _sums, _write

RUN = """
import json, sys
import tracklab
tracklab.configure()
sys.path.insert(0, sys.argv[1])
from test_runner import _sums
from tracklab.config import load_experiment
from tracklab.montecarlo import programs
programs.keep_in(sys.argv[2])
out = {path: {k: v.tolist() for k, v in _sums(load_experiment(path), 3).items()} for path in sys.argv[3:]}
out["loaded"] = programs.loaded
print(json.dumps(out))
"""


def _in_new_process(tmp_path, store, paths, jax_cache=None):
    """``RUN`` in a fresh process with the store in ``store`` and JAX's persistent cache in
    ``jax_cache`` (none by default)."""
    script = tmp_path / "run.py"
    script.write_text(RUN)
    env = {k: v for k, v in os.environ.items() if k != "JAX_COMPILATION_CACHE_DIR"}
    if jax_cache is not None:
        env["JAX_COMPILATION_CACHE_DIR"] = str(jax_cache)
        env["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = "0"
    done = subprocess.run([sys.executable, str(script), os.path.dirname(__file__), str(store), *map(str, paths)],
                          capture_output=True, text=True, check=True, env=env)
    return json.loads(done.stdout.strip().splitlines()[-1])


def test_a_program_kept_on_disk_gives_the_same_statistics_in_a_new_process(tmp_path):
    """Each world's program, compiled in one process and kept, is loaded by the next one (no
    tracing, no compiling) and gives the first process's sums exactly; the numbers are inputs,
    so a file with another value loads the same program. A truncated file in the folder is
    ignored: its program is compiled and written anew, and the next process loads it. A program
    JAX loaded from its own persistent cache (which serialises without some of its kernels) is
    never kept. The statistics are the same every time."""
    store, jax_cache = tmp_path / "programs", tmp_path / "jax"
    texts = {"tracking": TRACKING, "airborne": AIRBORNE, "servo": SERVO}
    paths = [_write(tmp_path, n, t) for n, t in texts.items()]
    tracking = str(paths[0])
    first = _in_new_process(tmp_path, store, paths, jax_cache)  # JAX's cache empty: XLA compiles each here
    kept = sorted(store.glob("*" + programs.SUFFIX))
    assert first["loaded"] == 0 and len(kept) == 3
    edited = _write(tmp_path, "edited", TRACKING.replace("sigma_r = 50.0", "sigma_r = 120.0"))
    second = _in_new_process(tmp_path, store, [*paths, edited])
    assert second["loaded"] == 3 and sorted(store.glob("*" + programs.SUFFIX)) == kept  # nothing new for the edit
    for path in map(str, paths):
        assert second[path] == first[path], path
    ref = _sums(load_experiment(edited), 3)  # compiled here, in this process
    for k, v in ref.items():
        np.testing.assert_allclose(second[str(edited)][k], v, rtol=1e-12, atol=1e-12, err_msg=k)
    for f in kept:  # every kept file truncated: the tracking world's is compiled again and written anew
        f.write_bytes(f.read_bytes()[:1000])
    again = _in_new_process(tmp_path, store, [tracking])
    assert again["loaded"] == 0 and sum(f.stat().st_size > 100_000 for f in kept) == 1
    loaded = _in_new_process(tmp_path, store, [tracking])
    assert loaded["loaded"] == 1
    other = tmp_path / "other"  # the program is in JAX's cache: JAX loads it, nothing is stored
    from_jax = _in_new_process(tmp_path, other, [tracking], jax_cache)
    assert from_jax["loaded"] == 0 and not list(other.glob("*" + programs.SUFFIX))
    for doc in (again, loaded, from_jax):
        assert doc[tracking] == first[tracking]


def test_a_filter_of_ones_own_is_kept_by_what_it_compiles_to(tmp_path):
    """A filter of one's own is structure by its traced code (``program_key``): another value of a
    number in its params is the same program, kept and found again; a number its factory bakes in
    is another program (never a stale one); a filter that calls back into Python is never kept."""
    import jax.numpy as jnp

    import tracklab
    from tracklab import Filter, FilterSpec, Out

    def walker(scale):  # a random-walk filter on [x, ẋ, y, ẏ] with `scale` compiled in, `q` an input
        def step(params, state, meas):
            x, P = state
            P = P + scale * params["q"] * jnp.eye(4)
            return (x, P), Out(x, P)
        return Filter(lambda params, prior: (prior.x, prior.P), step, {"q": jnp.asarray(1.0)})

    exp = load_experiment(Path(__file__).resolve().parents[1] / "experiments" / "own_filter.toml")

    def structure(flt):
        e = tracklab.experiment(exp.scenario, exp.sensor, [FilterSpec("walker", flt)], runs=2)
        return e, e.structure(chunk=2)

    e, base = structure(walker(1.0))
    _, again = structure(walker(1.0)._replace(params={"q": jnp.asarray(5.0)}))
    _, other = structure(walker(2.0))
    assert base == again and hash(base) == hash(again) and base != other

    def callback(params, state, meas):
        x, P = state
        return (x, P), Out(jax.pure_callback(lambda v: v, jax.ShapeDtypeStruct((4,), jnp.float64), x), P)

    _, called = structure(walker(1.0)._replace(step=callback))
    session = programs.folder()
    programs.keep_in(tmp_path / "programs")
    try:
        treedef = jax.tree_util.tree_structure(e.params())
        assert programs.key(called, treedef, (), 2, "float64", None) is None
        assert programs.key(base, treedef, (), 2, "float64", None) is not None
        e.monte_carlo(runs=2, chunk=2)
        assert len(list((tmp_path / "programs").glob("*" + programs.SUFFIX))) == 1
    finally:
        programs.keep_in(session)


def test_a_truth_and_a_sensor_of_ones_own_are_kept_by_what_they_trace_to():
    """Two truths (or sensors' h) written alike are one structure, one baking in another number is
    another; an experiment of them has a key in the store (nothing in it held by identity)."""
    import jax.numpy as jnp

    import tracklab
    from tracklab.scenarios import Generated
    from tracklab.sensors import CustomSensor

    def truth(speed):
        def draw(key):
            k = jnp.arange(21.0)
            return jnp.stack([1000.0 + speed * k, jnp.full_like(k, speed), 2000.0 + 0 * k, 0 * k], -1)
        return Generated(draw, dt=1.0, steps=20, dim=2).keyed()

    def radar(bias):
        h = lambda p: jnp.stack([jnp.hypot(p[0], p[1]) + bias, jnp.arctan2(p[1], p[0])])  # noqa: E731
        return CustomSensor(h, np.diag([100.0, 1e-6]), angles=(False, True), dim=2).keyed()

    assert truth(150.0) == truth(150.0) and truth(150.0) != truth(200.0)
    assert radar(0.0).h_fn == radar(0.0).h_fn and radar(0.0).h_fn != radar(5.0).h_fn
    exp = tracklab.experiment(truth(150.0), radar(0.0), [{"kind": "ekf", "label": "EKF"}], runs=2)
    again = tracklab.experiment(truth(150.0), radar(0.0), [{"kind": "ekf", "label": "EKF"}], runs=2)
    treedef = jax.tree_util.tree_structure(exp.params())
    assert exp.structure() == again.structure() and treedef == jax.tree_util.tree_structure(again.params())
    session = programs.folder()
    programs.keep_in(Path("/nonexistent-folder-never-written"))  # a key is made, nothing written
    try:
        assert programs.key(exp.structure(), treedef, (), 2, "float64", None) is not None
    finally:
        programs.keep_in(session)
