"""The public Python functions refuse bad input as the command line does: one ``ValueError`` or
``TypeError`` in one line naming the function, the argument and what is allowed, raised before
anything compiles (so these tests compile nothing but the one valid run)."""

import math

import numpy as np
import pytest

import tracklab
from tracklab import FilterResult, FilterSpec
from tracklab.checks import check_covariance, check_key
from tracklab.filters import build, ekf, kf, noise_params, strong_tracking
from tracklab.models import cv
from tracklab.scenarios import Crossing
from tracklab.sensors import Sensor

NAN, INF = math.nan, math.inf


def _kf1():
    """A 1-D constant-velocity KF: n = 2, m = 1."""
    m = cv(1, 1.0)
    return kf(m.F, np.array([[1.0, 0.0]]), np.asarray(m.Q(0.5)), np.array([[4.0]]))


def _refused(call, exc, function, argument):
    with pytest.raises(exc) as e:
        call()
    msg = str(e.value)
    assert function in msg and argument in msg, msg
    assert "\n" not in msg, msg
    return msg


# ------------------------------------------------------------------ run_filter

GOOD = dict(z=np.arange(6.0).reshape(3, 2)[:, :1], x0=np.zeros(2), P0=np.eye(2) * 10.0)
NONSYM = np.array([[10.0, 1.0], [0.0, 10.0]])
NEGDEF = -np.eye(2) * 10.0
INDEF = np.array([[1.0, 2.0], [2.0, 1.0]])


@pytest.mark.parametrize("change, exc, argument", [
    (dict(flt="kf"), TypeError, "flt"),
    (dict(flt=3), TypeError, "flt"),
    (dict(flt=None), TypeError, "flt"),
    (dict(P0=NONSYM), ValueError, "P0"),
    (dict(P0=NEGDEF), ValueError, "P0"),
    (dict(P0=INDEF), ValueError, "P0"),
    (dict(P0=np.zeros((2, 2))), ValueError, "P0"),
    (dict(P0=np.array([[NAN, 0.0], [0.0, 1.0]])), ValueError, "P0"),
    (dict(P0=np.array([[INF, 0.0], [0.0, 1.0]])), ValueError, "P0"),
    (dict(P0=np.eye(3)), ValueError, "P0"),
    (dict(P0="eye"), TypeError, "P0"),
    (dict(x0=np.array([NAN, 0.0])), ValueError, "x0[0]"),
    (dict(x0=np.array([0.0, INF])), ValueError, "x0[1]"),
    (dict(x0=np.array([0.0, -INF])), ValueError, "x0[1]"),
    (dict(z=np.array([[0.0], [INF], [1.0]])), ValueError, "z[1, 0]"),
    (dict(z=np.array([[0.0], [-INF], [1.0]])), ValueError, "z[1, 0]"),
    (dict(z=np.zeros(3)), ValueError, "z"),
    (dict(z=np.zeros((3, 3))), ValueError, "z"),  # three components, the filter measures one
    (dict(z=[["a"], ["b"]]), TypeError, "z"),
    (dict(precision="float16"), ValueError, "precision"),
    (dict(precision="64"), ValueError, "precision"),
    (dict(precision=None), ValueError, "precision"),
    (dict(dt=NAN), ValueError, "dt"),
    (dict(dt=INF), ValueError, "dt"),
    (dict(dt=0.0), ValueError, "dt"),
    (dict(dt=-1.0), ValueError, "dt"),
    (dict(dt="1"), TypeError, "dt"),
    (dict(dt=True), TypeError, "dt"),
])
def test_run_filter_refuses(change, exc, argument):
    args = dict(GOOD, flt=_kf1()) | change
    flt = args.pop("flt")
    z = args.pop("z")
    _refused(lambda: tracklab.run_filter(flt, z, **args), exc, "tracklab.run_filter", argument)


def _own_kf(F, H, Q, R):
    """A Kalman filter of one's own, written without tracklab's blocks: its arrays broadcast."""
    import jax.numpy as jnp

    def init(p, prior):
        return prior.x, prior.P

    def step(p, s, meas):
        x, P = p["F"] @ s[0], p["F"] @ s[1] @ p["F"].T + p["Q"]
        nu = meas.z - p["H"] @ x
        S = p["H"] @ P @ p["H"].T + p["R"]
        K = P @ p["H"].T @ jnp.linalg.inv(S)
        return (x + K @ nu, P - K @ S @ K.T), tracklab.Out(x=x, P=P, nu=nu, S=S)

    return tracklab.Filter(init, step, {k: jnp.asarray(v) for k, v in dict(F=F, H=H, Q=Q, R=R).items()})


@pytest.mark.parametrize("flt, n, m, takes", [
    (_kf1, 2, 3, 1),
    (lambda: _own_kf(cv(1, 1.0).F, np.array([[1.0, 0.0]]), np.asarray(cv(1, 1.0).Q(0.5)), np.array([[4.0]])), 2, 3, 1),
    (lambda: build("kf", cv(2, 1.0), SENSOR, noise_params(1.0, np.array([100.0, 100.0]))), 4, 3, 2),
    (lambda: build("ukf", cv(2, 1.0), Sensor("polar", 2, (10.0, 0.01)),
                   noise_params(1.0, np.array([100.0, 1e-4]))), 4, 1, 2),
    (lambda: build("sequential_ekf", cv(2, 1.0), Sensor("polar", 2, (10.0, 0.01)),
                   noise_params(1.0, np.array([100.0, 1e-4]))), 4, 3, 2),
])
def test_run_filter_refuses_z_of_another_size_than_the_filter_measures(flt, n, m, takes):
    """Without the check, such a z broadcasts against the filter's arrays (or a component is read past
    z's end) and the estimates are NaN: a built-in filter, one built with tracklab's blocks, or one
    written from scratch, the filter's size found by tracing it on shapes alone."""
    msg = _refused(lambda: tracklab.run_filter(flt(), np.zeros((10, m)), x0=np.zeros(n), P0=np.eye(n)), ValueError,
                   "tracklab.run_filter", "z")
    assert f"tracklab.run_filter: z = a (10, {m}) array: has m = {m} components per measurement, the filter takes " \
           f"{takes} " in msg, msg


@pytest.mark.parametrize("change, argument", [
    (dict(x0=np.array([[0.0, 0.0], [NAN, 0.0], [0.0, 0.0]])), "x0[1, 0]"),
    (dict(P0=np.stack([np.eye(2), NONSYM, np.eye(2)])), "P0[1]"),
    (dict(P0=np.stack([np.eye(2), np.eye(2), NEGDEF])), "P0[2]"),
    (dict(P0=np.stack([np.eye(2), np.eye(2), np.where(np.eye(2) > 0, NAN, 0.0)])), "P0[2]"),
    (dict(P0=np.stack([np.eye(2)] * 2)), "P0"),  # two priors for three recordings
])
def test_run_filter_checks_each_prior_of_a_batch(change, argument):
    args = dict(GOOD, z=np.zeros((3, 4, 1)), x0=np.zeros((3, 2)), P0=np.stack([np.eye(2)] * 3)) | change
    z = args.pop("z")
    _refused(lambda: tracklab.run_filter(_kf1(), z, **args), ValueError, "tracklab.run_filter", argument)


def test_a_refused_covariance_says_what_is_wrong():
    where = "tracklab.run_filter"
    assert "symmetric" in _refused(lambda: check_covariance(where, "P0", NONSYM), ValueError, where, "P0")
    assert "positive definite" in _refused(lambda: check_covariance(where, "P0", NEGDEF), ValueError, where, "P0")
    assert "finite" in _refused(lambda: check_covariance(where, "P0", np.full((2, 2), NAN)), ValueError, where, "P0")


def test_valid_covariances_pass():
    """Symmetric to rounding (float64 products, float32 input), batched, large or small scale."""
    rng = np.random.default_rng(0)
    A = rng.normal(size=(5, 4, 4))
    P = A @ np.swapaxes(A, -1, -2) + 1e-3 * np.eye(4)
    check_covariance("f", "P0", P)
    check_covariance("f", "P0", P * 1e12)
    check_covariance("f", "P0", P * 1e-12)
    P32 = (A.astype(np.float32) @ np.swapaxes(A, -1, -2).astype(np.float32)) + np.float32(1e-1) * np.eye(4, dtype=np.float32)
    P32[:, 0, 1] *= np.float32(1 + 2e-7)  # float32 rounding, not a user's asymmetry
    check_covariance("f", "P0", P32)
    check_covariance("f", "P0", [[4.0, 1.0], [1.0, 3.0]])


def test_run_filter_still_runs_valid_input():
    """A batch of two recordings with a prior each, a missed detection (a NaN row) and the
    filter's own params: runs, and the miss is predict-only."""
    z = np.array([[[0.0], [1.0], [NAN]], [[0.5], [NAN], [2.0]]])
    x0 = np.zeros((2, 2))
    P0 = np.stack([np.eye(2) * 10.0, np.array([[4.0, 1.0], [1.0, 3.0]])])
    res = tracklab.run_filter(_kf1(), z, x0=x0, P0=P0, params=None, dt=1.0, precision="float64")
    assert np.shape(res.x) == (2, 3, 2) and np.all(np.isfinite(res.x))
    assert not bool(res.valid[0, 2]) and not bool(res.valid[1, 1]) and bool(res.valid[1, 2])


# ------------------------------------------------------------------ filter factories

_M = cv(1, 1.0)
KF_ARGS = dict(F=_M.F, H=np.array([[1.0, 0.0]]), Q=np.asarray(_M.Q(0.5)), R=np.array([[4.0]]))


@pytest.mark.parametrize("change, exc, argument", [
    (dict(F="F"), TypeError, "F"),
    (dict(F=None), TypeError, "F"),
    (dict(F=np.eye(2) + 0j), TypeError, "F"),
    (dict(F=np.ones((2, 3))), ValueError, "F"),
    (dict(F=np.ones(2)), ValueError, "F"),
    (dict(F=np.array([[1.0, NAN], [0.0, 1.0]])), ValueError, "F[0, 1]"),
    (dict(H=np.ones((1, 3))), ValueError, "H"),
    (dict(H=np.array([1.0, 0.0])), ValueError, "H"),
    (dict(H=np.array([[INF, 0.0]])), ValueError, "H[0, 0]"),
    (dict(Q=KF_ARGS["Q"] * NAN), ValueError, "Q"),
    (dict(Q=-KF_ARGS["Q"]), ValueError, "Q"),
    (dict(Q=np.array([[1.0, 0.5], [0.0, 1.0]])), ValueError, "Q"),
    (dict(Q=np.eye(3)), ValueError, "Q"),
    (dict(Q="Q"), TypeError, "Q"),
    (dict(R=-KF_ARGS["R"]), ValueError, "R"),
    (dict(R=np.zeros((1, 1))), ValueError, "R"),
    (dict(R=np.eye(2)), ValueError, "R"),
    (dict(R=[[NAN]]), ValueError, "R"),
])
def test_kf_refuses(change, exc, argument):
    args = KF_ARGS | change
    msg = _refused(lambda: kf(**args), exc, "tracklab.filters.kf", f"{argument} = ")
    assert msg.startswith(f"tracklab.filters.kf: {argument} = "), msg


def test_kf_says_what_is_wrong_with_a_matrix():
    assert "positive semi-definite" in _refused(lambda: kf(**KF_ARGS | dict(Q=-KF_ARGS["Q"])), ValueError,
                                                "tracklab.filters.kf", "Q")
    assert "positive definite" in _refused(lambda: kf(**KF_ARGS | dict(R=-KF_ARGS["R"])), ValueError,
                                           "tracklab.filters.kf", "R")
    assert "(m, 2)" in _refused(lambda: kf(**KF_ARGS | dict(H=np.ones((1, 3)))), ValueError, "tracklab.filters.kf", "H")


def test_kf_takes_valid_models():
    """A singular process noise G Gᵀ q (positive semi-definite), none at all, lists, float32 arrays,
    and matrices traced inside jit (their shapes checked alone)."""
    import jax
    import jax.numpy as jnp

    G = np.array([[0.5], [1.0]])
    kf(**KF_ARGS | dict(Q=G @ G.T * 3.0))
    kf(**KF_ARGS | dict(Q=np.zeros((2, 2))))
    kf([[1.0]], [[1.0]], [[0.01]], [[1.0]])
    kf(*(jnp.asarray(v, jnp.float32) for v in KF_ARGS.values()))
    kf(np.eye(4), np.eye(4)[:2], np.eye(4) * 1e-12, np.diag([1e6, 1e-6]))
    jax.jit(lambda F: kf(F, KF_ARGS["H"], KF_ARGS["Q"], KF_ARGS["R"]).params["F"])(KF_ARGS["F"])


def _f(x):
    return x


def _h(x):
    return x[:1]


@pytest.mark.parametrize("factory", ["ekf", "strong_tracking"])
@pytest.mark.parametrize("change, exc, argument", [
    (dict(Q=KF_ARGS["Q"] * NAN), ValueError, "Q"),
    (dict(Q=-KF_ARGS["Q"]), ValueError, "Q"),
    (dict(Q=np.ones((2, 3))), ValueError, "Q"),
    (dict(R=-KF_ARGS["R"]), ValueError, "R"),
    (dict(R="R"), TypeError, "R"),
    (dict(f=KF_ARGS["F"]), TypeError, "f"),
    (dict(f=lambda x: x[:1]), ValueError, "f"),
    (dict(f=lambda x: np.sin(x)), ValueError, "f"),  # NumPy on a traced value: it cannot be differentiated
    (dict(h=lambda x: x), ValueError, "h"),  # two components, R is 1 x 1
    (dict(angle_mask=(True, False)), ValueError, "angle_mask"),
])
def test_ekf_and_strong_tracking_refuse(factory, change, exc, argument):
    args = dict(f=_f, h=_h, Q=KF_ARGS["Q"], R=KF_ARGS["R"]) | change
    where = f"tracklab.filters.{factory}"
    make = {"ekf": ekf, "strong_tracking": strong_tracking}[factory]
    msg = _refused(lambda: make(args.pop("f"), args.pop("h"), args.pop("Q"), args.pop("R"), **args), exc, where,
                   argument)
    assert msg.startswith(f"{where}: {argument}"), msg


@pytest.mark.parametrize("columns", [(1,), (1, 0), [0], (0, 2), ()])
def test_ekf_refuses_columns_that_leave_out_what_h_reads(columns):
    """h reads x[0] of a 2-state: (0,) or (0, 1) are the columns it may be given."""
    msg = _refused(lambda: ekf(_f, _h, KF_ARGS["Q"], KF_ARGS["R"], columns=columns), ValueError,
                   "tracklab.filters.ekf", "columns")
    assert msg.startswith("tracklab.filters.ekf: columns"), msg


@pytest.mark.parametrize("change, exc, argument", [
    (dict(rho=0.0), ValueError, "rho"),
    (dict(rho=1.5), ValueError, "rho"),
    (dict(rho=NAN), ValueError, "rho"),
    (dict(rho="0.9"), TypeError, "rho"),
    (dict(b=0.0), ValueError, "b"),
    (dict(b=-INF), ValueError, "b"),
])
def test_strong_tracking_refuses_its_factors(change, exc, argument):
    _refused(lambda: strong_tracking(_f, _h, KF_ARGS["Q"], KF_ARGS["R"], **change), exc,
             "tracklab.filters.strong_tracking", f"{argument} = ")


def test_ekf_and_strong_tracking_take_valid_models():
    G = np.array([[0.5], [1.0]])
    ekf(_f, _h, G @ G.T, KF_ARGS["R"], angle_mask=(True,))
    ekf(_f, _h, KF_ARGS["Q"], KF_ARGS["R"], angle_mask=[0])
    ekf(_f, _h, KF_ARGS["Q"], KF_ARGS["R"], columns=(0,))
    ekf(_f, _h, KF_ARGS["Q"], KF_ARGS["R"], columns=(0, 1))
    strong_tracking(_f, _h, [[0.01, 0.0], [0.0, 0.0]], [[1.0]], rho=1.0, b=2.5)


# ------------------------------------------------------------------ evaluate

def _recorded(N=2, T=4):
    rng = np.random.default_rng(1)
    truth = rng.normal(size=(N, T, 4))
    res = FilterResult(x=truth + 0.1, P=np.broadcast_to(np.eye(4), (N, T, 4, 4)), x_pred=None, nu=None, S=None,
                       valid=None, dof=None)
    return res, truth


@pytest.mark.parametrize("what, exc, argument", [
    ("filter in a dict", TypeError, "results['kf']"),
    ("string", TypeError, "results"),
    ("empty", ValueError, "results"),
    ("dt=0", ValueError, "dt"),
    ("dt=nan", ValueError, "dt"),
    ("dt=-inf", ValueError, "dt"),
    ("dt=None", TypeError, "dt"),
    ("truth nan", ValueError, "truth[0, 1, 2]"),
    ("truth inf", ValueError, "truth[1, 3, 0]"),
    ("window mask", ValueError, "windows['w']"),
])
def test_evaluate_refuses(what, exc, argument):
    res, truth = _recorded()
    results, kw = {"kf": res}, {"dt": 1.0}
    if what == "filter in a dict":
        results = {"kf": 3}
    elif what == "string":
        results = "kf"
    elif what == "empty":
        results = {}
    elif what.startswith("dt="):
        kw["dt"] = {"dt=0": 0, "dt=nan": NAN, "dt=-inf": -INF, "dt=None": None}[what]
    elif what == "truth nan":
        truth = truth.copy()
        truth[0, 1, 2] = NAN
    elif what == "truth inf":
        truth = truth.copy()
        truth[1, 3, 0] = INF
    elif what == "window mask":
        kw["windows"] = {"w": np.ones(3, bool)}
    _refused(lambda: tracklab.evaluate(results, truth, **kw), exc, "tracklab.evaluate", argument)


def _users_folder(tmp_path):
    folder = tmp_path / "ev"
    folder.mkdir()
    (folder / "notes.txt").write_text("mine")
    return folder


def test_evaluate_names_its_argument_out(tmp_path):
    """A folder of the user's is refused naming the function and its argument (not the command's --out)."""
    res, truth = _recorded()
    folder = _users_folder(tmp_path)
    msg = _refused(lambda: tracklab.evaluate({"kf": res}, truth, dt=1.0, out=folder), ValueError, "tracklab.evaluate",
                   "out")
    assert msg.startswith(f"tracklab.evaluate: out = '{folder}': is a folder tracklab did not write"), msg
    assert (folder / "notes.txt").read_text() == "mine"
    _refused(lambda: tracklab.evaluate({"kf": res}, truth, dt=1.0, out=3), TypeError, "tracklab.evaluate", "out")


# ------------------------------------------------------------------ monte_carlo

SENSOR = Sensor("cartesian", 2, (10.0, 10.0))


def _kf2():
    return build("kf", cv(2, 1.0), SENSOR, noise_params(1.0, np.array([100.0, 100.0])))


P0_CV = np.diag([30.0, 5.0, 30.0, 5.0]) ** 2


@pytest.mark.parametrize("change, exc, argument", [
    (dict(specs=[_kf2()]), TypeError, "specs[0]"),
    (dict(specs=["kf"]), TypeError, "specs[0]"),
    (dict(specs=[FilterSpec("kf", _kf2()), {"kind": "kf"}]), TypeError, "specs[1]"),
    (dict(specs=[FilterSpec("kf", tracklab.Filter("init", "step", {}))]), TypeError, "specs[0].filter"),
    (dict(specs=[]), ValueError, "specs"),
    (dict(specs=FilterSpec("kf", _kf2())), TypeError, "specs"),
    (dict(scenario="crossing"), TypeError, "scenario"),
    (dict(scenario=Crossing(dt=NAN, steps=5)), ValueError, "scenario.dt"),
    (dict(scenario=Crossing(dt=0.0, steps=5)), ValueError, "scenario.dt"),
    (dict(scenario=Crossing(dt=-1.0, steps=5)), ValueError, "scenario.dt"),
    (dict(scenario=Crossing(dt=1.0, steps=0)), ValueError, "scenario.steps"),
    (dict(runs=0), ValueError, "runs"),
    (dict(runs=-5), ValueError, "runs"),
    (dict(runs=2.5), TypeError, "runs"),
    (dict(runs=NAN), TypeError, "runs"),
    (dict(chunk=0), ValueError, "chunk"),
    (dict(precision="float16"), ValueError, "precision"),
    (dict(P0_cv=np.eye(2)), ValueError, "P0_cv"),
    (dict(P0_cv=-P0_CV), ValueError, "P0_cv"),
    (dict(P0_cv=P0_CV + np.triu(np.ones((4, 4)), 1)), ValueError, "P0_cv"),
    (dict(P0_cv=np.where(P0_CV > 100, NAN, P0_CV)), ValueError, "P0_cv"),
    (dict(params=[]), ValueError, "params"),
    (dict(windows={"w": np.ones(3, bool)}), ValueError, "windows['w']"),
    (dict(windows="w"), TypeError, "windows"),
    (dict(progress="print"), TypeError, "progress"),
    (dict(key=0.5), TypeError, "key"),
    (dict(key="0"), TypeError, "key"),
    (dict(key=None), TypeError, "key"),
    (dict(key=True), TypeError, "key"),
    (dict(key=-1), ValueError, "key"),
    (dict(key=2**64), ValueError, "key"),
    (dict(key=np.array([1, 2, 3], np.uint32)), TypeError, "key"),
    (dict(key=np.array([-1, 2])), ValueError, "key"),
    ("split", ValueError, "key"),
    ("rbg", ValueError, "key"),
])
def test_monte_carlo_refuses(change, exc, argument):
    import jax

    if change == "split":  # two keys
        change = dict(key=jax.random.split(jax.random.key(0)))
    elif change == "rbg":  # another generator than the simulation's
        change = dict(key=jax.random.key(0, impl="rbg"))
    args = dict(scenario=Crossing(dt=1.0, steps=5), sensor=SENSOR, specs=[FilterSpec("kf", _kf2())], runs=4,
                key=jax.random.key(0), P0_cv=P0_CV) | change
    _refused(lambda: tracklab.monte_carlo(**args), exc, "tracklab.monte_carlo", argument)


def test_every_key_form_is_the_same_key():
    """An integer seed s, jax.random.key(s) and the raw jax.random.PRNGKey(s) are one key: the same
    runs whichever is given (run i draws from fold_in(key, i)), an integer in either precision."""
    import jax

    for s in (0, 7, 2**31 + 3, 2**32 - 1, 2**40 + 5):
        with jax.enable_x64(True):
            want = np.asarray(jax.random.key_data(jax.random.key(s)))
            raw = jax.random.PRNGKey(s)
        for key in (s, np.uint32(s) if s < 2**32 else s, jax.random.wrap_key_data(raw), raw, np.asarray(raw)):
            got = check_key("tracklab.monte_carlo", "key", key)
            assert jax.dtypes.issubdtype(got.dtype, jax.dtypes.prng_key) and np.shape(got) == ()
            np.testing.assert_array_equal(np.asarray(jax.random.key_data(got)), want)


# ------------------------------------------------------------------ experiment

@pytest.mark.parametrize("change, argument", [
    (dict(scenario=Crossing(dt=NAN, steps=5)), "scenario.dt"),
    (dict(scenario=Crossing(dt=0.0, steps=5)), "scenario.dt"),
    (dict(scenario=Crossing(dt=INF, steps=5)), "scenario.dt"),
    (dict(scenario=Crossing(dt=1.0, steps=0)), "scenario.steps"),
    (dict(filters=[_kf2()]), "filters[0]"),
    (dict(filters=["kf"]), "filters[0]"),
    (dict(filters=FilterSpec("kf", _kf2())), "filters"),
    (dict(filters=[FilterSpec("kf", tracklab.Filter("init", "step", {}))]), "filters[0]"),
    (dict(precision="float16"), "precision"),
    (dict(precision=["float64"]), "precision"),
    (dict(chunk=0), "chunk"),
    (dict(runs=0), "runs"),
    (dict(runs=NAN), "runs"),
    (dict(prior={"pos_sigma": NAN}), "prior.pos_sigma"),
    (dict(prior={"vel_sigma": "10"}), "prior.vel_sigma"),
    (dict(prior="x"), "prior"),
    (dict(prior=[("pos_sigma", 1.0)]), "prior"),
    (dict(sensors=None), "sensors"),
    (dict(sensors="cartesian"), "sensors"),
    (dict(sensors=3), "sensors"),
    (dict(windows="x"), "windows"),
    (dict(window=3), "window"),
])
def test_experiment_refuses(change, argument):
    args = dict(scenario=Crossing(dt=1.0, steps=5), sensors=SENSOR, filters=[FilterSpec("kf", _kf2())], runs=4) | change
    _refused(lambda: tracklab.experiment(**args), ValueError, "tracklab.experiment", argument)


# ------------------------------------------------------------------ tune

@pytest.fixture(scope="module")
def small_experiment():
    return tracklab.experiment(Crossing(dt=1.0, steps=5), SENSOR, [{"kind": "kf", "label": "kf"}], runs=4)


@pytest.mark.parametrize("change, exc, argument", [
    (dict(exp="experiment.toml"), TypeError, "exp"),
    (dict(exp=None), TypeError, "exp"),
    (dict(names=3), TypeError, "names"),
    (dict(names=[3]), TypeError, "names"),
    (dict(steps=0), ValueError, "steps"),
    (dict(steps=1.5), TypeError, "steps"),
    (dict(lr=0.0), ValueError, "lr"),
    (dict(lr=NAN), ValueError, "lr"),
    (dict(lr=INF), ValueError, "lr"),
    (dict(runs_per_step=0), ValueError, "runs_per_step"),
    (dict(runs_per_step=NAN), TypeError, "runs_per_step"),
    (dict(eval_runs=-1), ValueError, "eval_runs"),
    (dict(seed=-1), ValueError, "seed"),
    (dict(every=0), ValueError, "every"),
    (dict(labels=["nope"]), ValueError, "labels"),
    (dict(labels="kf"), ValueError, "labels"),
    (dict(progress="print"), TypeError, "progress"),
    (dict(names={}), ValueError, "names"),
    (dict(names=[]), ValueError, "names"),
    (dict(names=""), ValueError, "names"),
    (dict(names={"kf": ""}), ValueError, "names"),
    (dict(names={"kf": []}), ValueError, "names"),
    (dict(names={"kf": 3}), TypeError, "names['kf']"),
    (dict(names={"kf": ["q", 3]}), TypeError, "names['kf']"),
    (dict(names={"kf": {3: "positive"}}), TypeError, "names['kf']"),
])
def test_tune_refuses(small_experiment, change, exc, argument):
    args = dict(exp=small_experiment, names=["q"], steps=1) | change
    exp, names = args.pop("exp"), args.pop("names")
    _refused(lambda: tracklab.tune(exp, names, **args), exc, "tracklab.tune", argument)


def test_tune_says_no_parameter_was_named(small_experiment):
    msg = _refused(lambda: tracklab.tune(small_experiment, {}), ValueError, "tracklab.tune", "names")
    assert msg.startswith("tracklab.tune: names = {}: names no parameter: must be a parameter name"), msg


def test_tune_takes_one_name_where_a_list_of_names_goes(small_experiment):
    """{label: "q"} is {label: ["q"]}, as "q" is ["q"]."""
    from tracklab.studies.tune import selection

    one = selection(small_experiment, {"kf": "q"})
    assert one == selection(small_experiment, {"kf": ["q"]}) == selection(small_experiment, "q") and list(one) == ["kf"]


# ------------------------------------------------------------------ an experiment's methods

@pytest.mark.parametrize("method", ["monte_carlo", "simulate", "run"])
@pytest.mark.parametrize("change, exc, argument", [
    (dict(runs=0), ValueError, "runs"),
    (dict(runs=-1), ValueError, "runs"),
    (dict(runs="8"), TypeError, "runs"),
    (dict(runs=2.0), TypeError, "runs"),
    (dict(runs=10**9), ValueError, "runs"),
    (dict(seed=-1), ValueError, "seed"),
    (dict(seed=2**32), ValueError, "seed"),
    (dict(seed="0"), TypeError, "seed"),
    (dict(precision="float16"), ValueError, "precision"),
    (dict(target_precision=2.0), ValueError, "target_precision"),
    (dict(target_precision="0.01"), TypeError, "target_precision"),
    (dict(progress="print"), TypeError, "progress"),
])
def test_an_experiments_methods_refuse(small_experiment, method, change, exc, argument):
    _refused(lambda: getattr(small_experiment, method)(**change), exc, f"Experiment.{method}", f"{argument} = ")


@pytest.mark.parametrize("method, change, exc, argument", [
    ("monte_carlo", dict(chunk=0), ValueError, "chunk"),
    ("monte_carlo", dict(chunk=1.5), TypeError, "chunk"),
    ("monte_carlo", "positional", ValueError, "runs"),
    ("run", dict(out=3), TypeError, "out"),
    ("run", dict(max_memory="8G"), TypeError, "max_memory"),
    ("run", dict(max_memory=0), ValueError, "max_memory"),
])
def test_an_experiments_methods_refuse_their_own_arguments(small_experiment, method, change, exc, argument):
    call = (lambda: small_experiment.monte_carlo(-3)) if change == "positional" else (
        lambda: getattr(small_experiment, method)(**change))
    _refused(call, exc, f"Experiment.{method}", f"{argument} = ")


def test_every_worlds_methods_check_their_arguments():
    from tracklab.worlds.airborne.experiment import AirborneExperiment
    from tracklab.worlds.protocol import CHECKED_METHODS
    from tracklab.worlds.servo.experiment import ServoExperiment
    from tracklab.worlds.tracking.experiment import Experiment

    for cls in (Experiment, AirborneExperiment, ServoExperiment):
        for name in CHECKED_METHODS:
            if hasattr(cls, name):
                assert getattr(getattr(cls, name), "checks_arguments", False), (cls.__name__, name)


def test_run_names_its_argument_out(small_experiment, tmp_path):
    folder = _users_folder(tmp_path)
    msg = _refused(lambda: small_experiment.run(out=folder), ValueError, "Experiment.run", "out")
    assert msg.startswith(f"Experiment.run: out = '{folder}': is a folder tracklab did not write"), msg
