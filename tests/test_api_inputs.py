"""The public Python functions refuse bad input as the command line does: one ``ValueError`` or
``TypeError`` in one line naming the function, the argument and what is allowed, raised before
anything compiles (so these tests compile nothing but the one valid run)."""

import math

import numpy as np
import pytest

import tracklab
from tracklab import FilterResult, FilterSpec
from tracklab.checks import check_covariance
from tracklab.filters import build, kf, noise_params
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
])
def test_monte_carlo_refuses(change, exc, argument):
    import jax

    args = dict(scenario=Crossing(dt=1.0, steps=5), sensor=SENSOR, specs=[FilterSpec("kf", _kf2())], runs=4,
                key=jax.random.key(0), P0_cv=P0_CV) | change
    _refused(lambda: tracklab.monte_carlo(**args), exc, "tracklab.monte_carlo", argument)


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
])
def test_tune_refuses(small_experiment, change, exc, argument):
    args = dict(exp=small_experiment, names=["q"], steps=1) | change
    exp, names = args.pop("exp"), args.pop("names")
    _refused(lambda: tracklab.tune(exp, names, **args), exc, "tracklab.tune", argument)
