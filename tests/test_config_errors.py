"""A corpus of broken experiment files: each one is refused up front.

Every case starts from a small valid experiment (crossing scenario, polar
sensor, one EKF, 20 runs, 10 steps), breaks one thing, and checks that
``load_experiment`` raises ``ConfigError`` with a one-line message naming the
file, the field and the bad value.
"""

from __future__ import annotations

import copy
import json
import math

import pytest

from tracklab.config import load_experiment
from tracklab.errors import ConfigError

FILE = "broken.toml"
CSV = "flight.csv"

BASE = {
    "experiment": {"name": "small", "runs": 20, "seed": 0, "dt": 0.5, "steps": 10},
    "scenario": {"kind": "crossing"},
    "sensor": {"kind": "polar", "sigma_r": 100.0, "sigma_angle": 0.003},
    "filter": [{"kind": "ekf", "label": "EKF"}],
}

# a valid trajectory file: 10 s of a straight 3-D flight, one row per second
GOOD_CSV = "t,x,y,z\n" + "".join(f"{t},{1000.0 + 200.0 * t},{5000.0},{300.0}\n" for t in range(11))

TRAJ = {
    "experiment": {"name": "traj", "runs": 20, "seed": 0, "dt": 0.5, "steps": 10},
    "scenario": {"kind": "trajectory", "path": CSV},
    "sensor": {"kind": "cartesian", "sigma": 10.0},
    "filter": [{"kind": "kf", "label": "KF"}],
}


# --- a tiny TOML writer (tomllib reads only) ---------------------------------------------


def _value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v)  # JSON string escapes are valid TOML basic-string escapes
    if isinstance(v, list):
        return "[" + ", ".join(_value(x) for x in v) + "]"
    raise TypeError(v)


def _table(d) -> str:
    return "".join(f"{k} = {_value(v)}\n" for k, v in d.items())


def to_toml(cfg: dict) -> str:
    out = []
    for name, body in cfg.items():
        if isinstance(body, list) and all(isinstance(t, dict) for t in body) and body:
            out += [f"[[{name}]]\n{_table(t)}" for t in body]
        elif isinstance(body, dict):
            out.append(f"[{name}]\n{_table(body)}")
        else:
            out.insert(0, f"{name} = {_value(body)}\n")  # top-level keys come first
    return "\n".join(out)


def edit(base=BASE, *, drop=(), **changes):
    """A copy of ``base`` with ``section__key=value`` changes and dotted ``drop`` keys removed.

    ``filter1__kind`` edits the first [[filter]] table; a change whose key has no ``__``
    replaces a whole section.
    """
    cfg = copy.deepcopy(base)
    for key, v in changes.items():
        if "__" not in key:
            cfg[key] = v
            continue
        sec, field = key.split("__", 1)
        if sec.startswith("filter") and sec != "filter":
            cfg["filter"][int(sec[6:]) - 1][field] = v
        else:
            cfg.setdefault(sec, {})[field] = v
    for key in drop:
        if "." in key:
            sec, field = key.split(".", 1)
            cfg[sec].pop(field)
        else:
            cfg.pop(key)
    return cfg


def plus_filter(base=BASE, **table):
    cfg = copy.deepcopy(base)
    cfg["filter"].append(table)
    return cfg


def traj(csv_text=GOOD_CSV, **changes):
    return {"cfg": edit(TRAJ, **changes), "csv": csv_text}




# an angle-tracking experiment (paper 004): overflight seen by an alt-azimuth mount
MOUNT = {
    "experiment": {"name": "mount", "runs": 20, "seed": 0, "dt": 0.04, "steps": 100},
    "scenario": {"kind": "overflight"},
    "sensor": {"kind": "mount", "sigma_az": 0.02, "sigma_el": 0.02},
    "filter": [{"kind": "kf", "label": "KF", "model": "ca", "q": 2e-6}],
}


# a servo experiment (paper 003): the closed azimuth loop
SERVO = {
    "experiment": {"name": "servo", "runs": 2, "seed": 0},
    "servo": {"frames": 100, "settle": 0.1},
    "target": {"kind": "sine"},
    "estimator": [{"label": "KF", "kind": "kf"}],
    "case": [{"mode": "on_axis", "estimator": "KF"}],
}
# an airborne-radar experiment (paper 001): the four-coordinate tracker in the antenna frame
AIRBORNE = {
    "experiment": {"name": "airborne", "runs": 2, "seed": 0},
    "airborne": {"duration": 2.0},
    "tracker": [{"label": "EKF", "kind": "cd_ekf"}],
}
SINE = {
    "experiment": {"name": "sine", "runs": 2, "seed": 0, "dt": 0.01, "steps": 50},
    "scenario": {"kind": "sine"},
    "sensor": {"kind": "cartesian", "sigma": 0.003},
    "filter": [{"kind": "dekf"}],
}


def mount(**changes):
    return edit(MOUNT, **changes)


def windows(text):
    """The mount experiment with a [report.windows] table (nested tables need raw TOML)."""
    return to_toml(MOUNT) + "\n[report.windows]\n" + text + "\n"


def case(id, spec, field, value, *more, marks=()):
    """spec: a config dict, raw TOML text, or {'cfg': ..., 'csv': ...}; value: repr of the bad value."""
    return pytest.param(spec, field, value, more, id=id, marks=marks)


CASES = [
    # --- unknown kinds ------------------------------------------------------------------
    case("filter-kind-unknown", edit(filter1__kind="particle"), "filter[1].kind", "'particle'", "ekf"),
    case("filter-kind-unknown-second", plus_filter(kind="particle", label="PF"), "filter[2].kind", "'particle'"),
    case("sensor-kind-unknown", edit(sensor__kind="sonar"), "sensor.kind", "'sonar'", "polar"),
    case("scenario-kind-unknown", edit(scenario__kind="spiral"), "scenario.kind", "'spiral'", "crossing"),
    case("model-unknown", edit(filter1__model="singer9"), "filter[1].model", "'singer9'", "cv"),
    case("debias-unknown", edit(filter1__kind="cmkf", filter1__debias="magic"), "filter[1].debias", "'magic'"),
    # --- non-positive variances -----------------------------------------------------------
    case("sigma-negative", edit(sensor__sigma_r=-100.0), "sensor.sigma_r", "-100.0", "> 0"),
    case("sigma-zero", edit(sensor__sigma_angle=0.0), "sensor.sigma_angle", "0.0", "> 0"),
    case("sigma-int-zero", edit(sensor__sigma_r=0), "sensor.sigma_r", "= 0:"),  # as the file writes it
    case("filter-sigma-negative", edit(filter1__sigma_r=-1.0), "filter[1].sigma_r", "-1.0"),
    case("filter-accel-sigma-zero", edit(filter1__accel_sigma=0.0), "filter[1].accel_sigma", "0.0"),
    case("scenario-accel-sigma-negative", edit(scenario__accel_sigma=-1.0), "scenario.accel_sigma", "-1.0"),
    case("prior-pos-sigma-negative", edit(prior__pos_sigma=-5.0), "prior.pos_sigma", "-5.0"),
    case("prior-vel-sigma-zero", edit(prior__vel_sigma=0.0), "prior.vel_sigma", "0.0"),
    case("cartesian-sigma-zero", traj(sensor__sigma=0.0), "sensor.sigma", "0.0"),
    case("cartesian-sigma-list-negative", traj(sensor__sigma=[10.0, -1.0, 10.0]),
         "sensor.sigma", "[10.0, -1.0, 10.0]"),
    case("dt-zero", edit(experiment__dt=0.0), "experiment.dt", "0.0"),
    case("dt-negative", edit(experiment__dt=-0.5), "experiment.dt", "-0.5"),
    case("p-detect-zero", edit(sensor__p_detect=0.0), "sensor.p_detect", "0.0"),
    case("p-detect-above-one", edit(sensor__p_detect=1.5), "sensor.p_detect", "1.5"),
    # --- NaN / inf --------------------------------------------------------------------------
    case("sigma-nan", edit(sensor__sigma_r=math.nan), "sensor.sigma_r", "nan", "finite"),
    case("sigma-inf", edit(sensor__sigma_angle=math.inf), "sensor.sigma_angle", "inf", "finite"),
    case("dt-minus-inf", edit(experiment__dt=-math.inf), "experiment.dt", "-inf"),
    case("speed-nan", edit(scenario__speed=math.nan), "scenario.speed", "nan"),
    case("altitude-inf", edit(scenario__altitude=math.inf), "scenario.altitude", "inf"),
    case("filter-accel-sigma-nan", edit(filter1__accel_sigma=math.nan), "filter[1].accel_sigma", "nan"),
    case("prior-acc-sigma-inf", edit(prior__acc_sigma=math.inf), "prior.acc_sigma", "inf"),
    case("runs-nan", edit(experiment__runs=math.nan), "experiment.runs", "nan", "integer"),
    case("cartesian-sigma-nan", traj(sensor__sigma=math.nan), "sensor.sigma", "nan"),
    case("p-detect-nan", edit(sensor__p_detect=math.nan), "sensor.p_detect", "nan"),
    # --- wrong types --------------------------------------------------------------------------
    case("string-for-number", edit(sensor__sigma_r="100"), "sensor.sigma_r", "'100'", "number"),
    case("bool-for-number", edit(experiment__dt=True), "experiment.dt", "true", "number"),
    case("bool-for-filter-number", edit(filter1__accel_sigma=False), "filter[1].accel_sigma", "false"),
    case("float-for-integer-runs", edit(experiment__runs=20.5), "experiment.runs", "20.5", "integer"),
    case("whole-float-for-integer-runs", edit(experiment__runs=20.0), "experiment.runs", "20.0", "integer"),
    case("bool-for-integer-runs", edit(experiment__runs=True), "experiment.runs", "true", "integer"),
    case("string-for-integer-steps", edit(experiment__steps="10"), "experiment.steps", "'10'", "integer"),
    case("list-for-number", edit(sensor__sigma_angle=[0.003]), "sensor.sigma_angle", "[0.003]"),
    case("number-for-string-kind", edit(filter1__kind=3), "filter[1].kind", "3", "string"),
    case("number-for-label", edit(filter1__label=5), "filter[1].label", "5", "string"),
    case("number-for-name", edit(experiment__name=7), "experiment.name", "7", "string"),
    case("string-for-seed", edit(experiment__seed="zero"), "experiment.seed", "'zero'"),
    case("seed-negative", edit(experiment__seed=-1), "experiment.seed", "-1"),
    case("seed-too-big", edit(experiment__seed=2**32), "experiment.seed", str(2**32)),
    case("string-for-cartesian-sigma", traj(sensor__sigma="10"), "sensor.sigma", "'10'"),
    case("bool-in-cartesian-sigma-list", traj(sensor__sigma=[10.0, True, 10.0]),
         "sensor.sigma", "[10.0, True, 10.0]"),
    case("section-is-a-string", 'sensor = "polar"\n' + to_toml(edit(drop=["sensor"])), "sensor", "'polar'", "table"),
    case("filter-is-a-table", edit(filter={"kind": "ekf"}), "[[filter]]", "{'kind': 'ekf'}"),
    case("filter-entry-not-a-table", 'filter = ["ekf"]\n' + to_toml(edit(drop=["filter"])), "filter[1]", "'ekf'"),
    # --- missing required fields / sections ---------------------------------------------------
    case("missing-name", edit(drop=["experiment.name"]), "experiment.name", "(missing)", "required"),
    case("missing-runs", edit(drop=["experiment.runs"]), "experiment.runs", "(missing)", "required"),
    case("missing-dt", edit(drop=["experiment.dt"]), "experiment.dt", "(missing)", "required"),
    case("missing-steps", edit(drop=["experiment.steps"]), "experiment.steps", "(missing)", "required"),
    case("missing-sensor-kind", edit(drop=["sensor.kind"]), "sensor.kind", "(missing)", "required"),
    case("missing-sensor-sigma", edit(drop=["sensor.sigma_angle"]), "sensor.sigma_angle", "(missing)", "required"),
    case("missing-cartesian-sigma", traj(drop=["sensor.sigma"]),
         "sensor.sigma", "(missing)", "required"),
    case("missing-scenario-kind", edit(drop=["scenario.kind"]), "scenario.kind", "(missing)", "required"),
    case("missing-filter-kind", edit(filter=[{"label": "EKF"}]), "filter[1].kind", "(missing)", "required"),
    case("missing-trajectory-path", traj(drop=["scenario.path"]),
         "scenario.path", "(missing)", "required"),
    case("missing-section-experiment", edit(drop=["experiment"]), "[experiment]", "(missing)", "required"),
    case("missing-section-scenario", edit(drop=["scenario"]), "[scenario]", "(missing)", "required"),
    case("missing-section-sensor", edit(drop=["sensor"]), "[sensor]", "(missing)", "required"),
    case("missing-filters", edit(drop=["filter"]), "[[filter]]", "(missing)", "filter"),
    case("empty-file", "", "[experiment]", "(missing)", "required"),
    # --- unknown fields and sections -------------------------------------------------------------
    case("unknown-field-filter-typo", edit(filter1__sigma_rr=50.0), "filter[1].sigma_rr", "50.0", "unknown field"),
    case("unknown-field-sensor-typo", edit(sensor__sigma_angel=0.003), "sensor.sigma_angel", "0.003", "unknown field"),
    case("unknown-field-experiment", edit(experiment__run=20), "experiment.run", "20", "unknown field"),
    case("unknown-field-scenario", edit(scenario__sped=400.0), "scenario.sped", "400.0", "unknown field"),
    case("unknown-field-prior", edit(prior__pos=1.0), "prior.pos", "1.0", "unknown field"),
    case("unknown-field-report", edit(report__windos=[1, 10]), "report.windos", "[1, 10]", "unknown field"),
    case("filter-sigma-with-polar-sensor", edit(filter1__sigma=10.0), "filter[1].sigma", "10.0", "unknown field"),
    case("ca-model-with-cv-noise-field", edit(filter1__model="ca", filter1__accel_sigma=1.0),
         "filter[1].accel_sigma", "1.0", "unknown field"),
    case("unknown-section", edit(reprot={"window": [1, 10]}), "[reprot]", "", "unknown section"),
    # --- absurd sizes --------------------------------------------------------------------------
    case("runs-1e12", edit(experiment__runs=10**12), "experiment.runs", "1000000000000"),
    case("runs-zero", edit(experiment__runs=0), "experiment.runs", "0"),
    case("runs-negative", edit(experiment__runs=-5), "experiment.runs", "-5"),
    case("steps-too-large", edit(experiment__steps=10**7), "experiment.steps", "10000000"),
    case("steps-zero", edit(experiment__steps=0), "experiment.steps", "0"),
    case("runs-times-steps-too-large", edit(experiment__runs=10**8, experiment__steps=10**6),
         "experiment.runs", "100000000", "runs x steps"),
    case("chunk-zero", edit(experiment__chunk=0), "experiment.chunk", "0"),
    # --- dimension mismatch -------------------------------------------------------------------
    case("spherical-with-2d-crossing", edit(sensor={"kind": "spherical", "sigma_r": 100.0, "sigma_az": 0.003,
                                                   "sigma_el": 0.003}), "sensor.kind", "'spherical'", "altitude"),
    case("polar-with-altitude", edit(scenario__altitude=3000.0), "sensor.kind", "'polar'", "altitude"),
    case("cartesian-sigma-wrong-length", edit(sensor={"kind": "cartesian", "sigma": [10.0, 10.0, 10.0]}),
         "sensor.sigma", "[10.0, 10.0, 10.0]", "2 values"),
    case("cartesian-filter-sigma-wrong-length",
         edit(sensor={"kind": "cartesian", "sigma": 10.0}, filter=[{"kind": "kf", "sigma": [10.0, 10.0, 10.0]}]),
         "filter[1].sigma", "[10.0, 10.0, 10.0]"),
    case("spherical-with-2d-trajectory", {"cfg": edit(TRAJ, scenario__dims=2, sensor={
        "kind": "spherical", "sigma_r": 10.0, "sigma_az": 0.001, "sigma_el": 0.001}, filter=[{"kind": "ekf"}]),
        "csv": GOOD_CSV}, "scenario.dims", "2"),
    case("trajectory-dims-4", traj(scenario__dims=4), "scenario.dims", "4"),
    # --- filter kind vs sensor ---------------------------------------------------------------
    case("kf-with-polar", edit(filter1__kind="kf"), "filter[1].kind", "'kf'", "cartesian"),
    case("cmkf-additive-with-spherical", edit(
        scenario__altitude=3000.0, sensor={"kind": "spherical", "sigma_r": 100.0, "sigma_az": 0.003, "sigma_el": 0.003},
        filter=[{"kind": "cmkf", "debias": "additive"}]), "filter[1].debias", "'additive'", "spherical"),
    case("polar-kf-with-spherical", edit(
        scenario__altitude=3000.0, sensor={"kind": "spherical", "sigma_r": 100.0, "sigma_az": 0.003, "sigma_el": 0.003},
        filter=[{"kind": "polar_kf"}]), "filter[1].kind", "'polar_kf'", "polar"),
    case("cmkf-with-cartesian", edit(sensor={"kind": "cartesian", "sigma": 10.0}, filter=[{"kind": "cmkf"}]),
         "filter[1].kind", "'cmkf'"),
    case("polar-kf-with-ca-model", edit(filter1__kind="polar_kf", filter1__model="ca"), "filter[1].model", "'ca'"),
    # --- report window ------------------------------------------------------------------------
    case("window-starts-at-zero", edit(report__window=[0, 10]), "report.window", "[0, 10]", "1 <= first"),
    case("window-reversed", edit(report__window=[8, 3]), "report.window", "[8, 3]"),
    case("window-past-steps", edit(report__window=[1, 11]), "report.window", "[1, 11]", "10"),
    case("window-one-value", edit(report__window=[5]), "report.window", "[5]"),
    case("window-floats", edit(report__window=[1.0, 10.0]), "report.window", "[1.0, 10.0]"),
    case("window-bools", edit(report__window=[True, 10]), "report.window", "[True, 10]"),
    case("window-string", edit(report__window="all"), "report.window", "'all'"),
    # --- labels and names -----------------------------------------------------------------------
    case("duplicate-labels", plus_filter(kind="sequential_ekf", label="EKF"), "filter[2].label", "'EKF'", "unique"),
    case("duplicate-default-labels", edit(filter=[{"kind": "ekf"}, {"kind": "ekf"}]), "filter[2].label", "'ekf'",
         "unique"),
    case("blank-label", edit(filter1__label="  "), "filter[1].label", "'  '", "empty"),
    case("name-with-slash", edit(experiment__name="a/b"), "experiment.name", "'a/b'"),
    case("name-dotdot", edit(experiment__name=".."), "experiment.name", "'..'"),
    case("name-empty", edit(experiment__name=""), "experiment.name", "''"),
    case("name-with-space", edit(experiment__name="my run"), "experiment.name", "'my run'"),
    case("name-too-long", edit(experiment__name="a" * 101), "experiment.name", "a" * 101),
    case("name-trailing-newline", edit(experiment__name="abc\n"), "experiment.name", r"'abc\n'"),
    # --- file-level problems -------------------------------------------------------------------
    case("toml-syntax", "[experiment\nname = 'x'\n", "file", "", "not valid TOML"),
    case("toml-missing-value", to_toml(BASE).replace("runs = 20", "runs = "), "file", "", "not valid TOML"),
    case("toml-duplicate-key", to_toml(BASE).replace("runs = 20", "runs = 20\nruns = 30"), "file", "",
         "not valid TOML"),
    case("toml-not-utf8", b"[experiment]\nname = \"caf\xe9\"\n", "file", "", "cannot be read"),
    # --- trajectory files ----------------------------------------------------------------------
    case("trajectory-missing-file", {"cfg": edit(TRAJ, scenario__path="nowhere.csv"), "csv": None},
         "scenario.path", "'nowhere.csv'", "does not exist"),
    case("trajectory-path-is-folder", traj(scenario__path="."),
         "scenario.path", "'.'"),
    case("csv-empty", traj(""), "scenario.path", repr(CSV), "empty"),
    case("csv-comments-only", traj("# nothing here\n\n"), "scenario.path", repr(CSV), "empty"),
    case("csv-header-wrong", traj(GOOD_CSV.replace("t,x,y,z", "time,x,y,z")), "scenario.path", repr(CSV), "header"),
    case("csv-header-missing", traj(GOOD_CSV.split("\n", 1)[1]), "scenario.path", repr(CSV), "header"),
    case("csv-header-3-columns", traj("t,x,y\n0,1,2\n1,2,3\n"), "scenario.path", repr(CSV), "header"),
    case("csv-non-numeric", traj(GOOD_CSV.replace("\n3,", "\nthree,")), "scenario.path", repr(CSV), "not numeric"),
    case("csv-empty-cell", traj(GOOD_CSV.replace("\n3,1600.0,", "\n3,,")), "scenario.path", repr(CSV), "not numeric"),
    case("csv-wrong-column-count", traj(GOOD_CSV.replace("\n3,1600.0,", "\n3,")), "scenario.path", repr(CSV),
         "columns"),
    case("csv-nan", traj(GOOD_CSV.replace("\n3,1600.0,", "\n3,nan,")), "scenario.path", repr(CSV), "NaN"),
    case("csv-inf", traj(GOOD_CSV.replace(",5000.0,300.0\n4,", ",5000.0,inf\n4,")), "scenario.path", repr(CSV),
         "finite"),
    case("csv-time-decreasing", traj(GOOD_CSV.replace("\n3,", "\n1.5,")), "scenario.path", repr(CSV), "increasing"),
    case("csv-time-repeated", traj(GOOD_CSV.replace("\n3,", "\n2,")), "scenario.path", repr(CSV), "increasing"),
    case("csv-single-row", traj("t,x,y,z\n0,1000,5000,300\n"), "scenario.path", repr(CSV), "at least 2"),
    case("csv-header-only", traj("t,x,y,z\n"), "scenario.path", repr(CSV), "at least 2"),
    case("csv-binary", {"cfg": edit(TRAJ), "csv": b"\x89PNG\r\n\x1a\n\xff\xfe\x00"}, "scenario.path", repr(CSV),
         "cannot be read"),
    # 10 s of file at dt = 0.5 s holds 20 steps
    case("steps-longer-than-trajectory", traj(experiment__steps=21), "experiment.steps", "21", "at most 20"),
    case("trajectory-start-past-end", traj(scenario__start=9.0), "experiment.steps", "10", "at most 2"),
    case("trajectory-start-negative", traj(scenario__start=-1.0), "scenario.start", "-1.0"),
    # --- angle tracking: overflight, mount, STF, error space, prediction windows ---------------
    case("overflight-elevation-95", mount(scenario__max_elevation=95.0), "scenario.max_elevation", "95.0", "(0, 90)"),
    case("overflight-negative-altitude", mount(scenario__altitude=-1.0), "scenario.altitude", "-1.0", "> 0"),
    case("mount-on-2d-crossing", mount(scenario={"kind": "crossing"}), "sensor.kind", "mount", "3-D"),
    case("mount-beside-polar", edit(MOUNT, scenario={"kind": "crossing", "altitude": 1000.0}, sensor=[
        {"kind": "mount", "sigma_az": 0.02, "sigma_el": 0.02},
        {"kind": "spherical", "sigma_r": 10.0, "sigma_az": 0.001, "sigma_el": 0.001}]), "[[sensor]]", "mount", "other kinds"),
    case("mount-sigma-zero", mount(sensor__sigma_el=0.0), "sensor.sigma_el", "0.0", "> 0"),
    case("stf-rho-above-1", mount(filter=[{"kind": "stf", "model": "ca", "rho": 1.5}]), "filter[1].rho", "1.5", "(0, 1]"),
    case("stf-rho-zero", mount(filter=[{"kind": "stf", "model": "ca", "rho": 0.0}]), "filter[1].rho", "0.0", "(0, 1]"),
    case("stf-b-negative", mount(filter=[{"kind": "stf", "model": "ca", "b": -1.0}]), "filter[1].b", "-1.0", "> 0"),
    case("error-space-unknown-guide", mount(filter=[{"kind": "error_space", "guide": "radar"}]), "filter[1].guide", "radar",
         "sensor name"),
    case("error-space-delay-without-guide", mount(filter=[{"kind": "error_space", "guide_delay": 2}]),
         "filter[1].guide_delay", "2", "external guide"),
    case("error-space-negative-delay", edit(MOUNT, sensor=[
        {"kind": "mount", "name": "a", "sigma_az": 0.02, "sigma_el": 0.02},
        {"kind": "mount", "name": "g", "sigma_az": 0.1, "sigma_el": 0.1}],
        filter=[{"kind": "error_space", "guide": "g", "guide_delay": -1}]), "filter[1].guide_delay", "-1", "integer"),
    case("error-space-on-polar", plus_filter(kind="error_space"), "filter[2].kind", "error_space", "cartesian"),
    case("error-space-sees-two-sensors", edit(MOUNT, sensor=[
        {"kind": "mount", "name": "a", "sigma_az": 0.02, "sigma_el": 0.02},
        {"kind": "mount", "name": "b", "sigma_az": 0.1, "sigma_el": 0.1}],
        filter=[{"kind": "error_space"}]), "filter[1].sensors", "['a', 'b']", "one sensor"),
    case("q-and-sigma-both", mount(filter=[{"kind": "kf", "model": "ca", "q": 1e-6, "accel_increment_sigma": 0.1}]),
         "filter[1].q", "1e-06", "not both"),
    case("q-negative", mount(filter=[{"kind": "kf", "model": "ca", "q": -1e-6}]), "filter[1].q", "-1e-06", "> 0"),
    case("r-wrong-length", mount(filter=[{"kind": "kf", "model": "ca", "r": [1e-4, 1e-4, 1e-4]}]), "filter[1].r",
         "[0.0001, 0.0001, 0.0001]", "2 values"),
    case("r-and-sigma-both", mount(filter=[{"kind": "kf", "model": "ca", "r": 1e-4, "sigma_az": 0.01}]), "filter[1].r",
         "0.0001", "not both"),
    case("window-reversed", windows('a = [5.0, 1.0]'), "report.windows.a", "[5.0, 1.0]", "t0 <= t1"),
    case("window-outside-the-run", windows('late = [100.0, 200.0]'), "report.windows.late", "[100.0, 200.0]", "no step"),
    case("window-two-rests", windows('a = "rest"\nb = "rest"'), "report.windows.b", "rest", "only one"),
    case("window-reserved-name", windows('window = [1.0, 2.0]'), "report.windows.window", "window", "not 'window'"),
    case("window-nan", windows('a = [nan, 2.0]'), "report.windows.a", "nan", "seconds"),
    case("windows-not-a-table", to_toml(mount(report={"windows": [1, 2]})), "report.windows", "[1, 2]", "table"),
    # --- servo experiments and the dual EKF ---------------------------------------------------------
    case("servo-unknown-mode", edit(SERVO, case=[{"mode": "triple_loop"}]), "case[1].mode", "triple_loop", "on_axis"),
    case("servo-unknown-estimator", edit(SERVO, case=[{"mode": "on_axis", "estimator": "UKF"}]), "case[1].estimator", "UKF",
         "perfect"),
    case("servo-lag-without-estimator", edit(SERVO, case=[{"mode": "velocity_lag"}]), "case[1].estimator", "(missing)",
         "needs an estimator"),
    case("servo-settle-too-long", edit(SERVO, servo__settle=5.0), "servo.settle", "5.0", "shorter than the run"),
    case("servo-cone-angle-zero", edit(SERVO, target={"kind": "cone", "half_angle": 0.0}), "target.half_angle", "0.0", "> 0"),
    case("servo-forgetting-above-1", edit(SERVO, estimator=[{"label": "D", "kind": "dekf", "lam": 1.5}]),
         "estimator[1].lam", "1.5", "(0, 1]"),
    case("servo-no-case", edit(SERVO, drop=["case"]), "[case]", "(missing)", "required"),
    case("servo-unknown-section", edit(SERVO, sensor={"kind": "polar"}), "[sensor]", "...", "servo experiment"),
    case("servo-delay-zero", edit(SERVO, servo__delay=0), "servo.delay", "0", "integer in [1"),
    case("dekf-on-a-mount", edit(MOUNT, filter=[{"kind": "dekf"}]), "filter[1].kind", "dekf", "cartesian"),
    case("dekf-on-3d", traj(filter=[{"kind": "dekf"}]), "filter[1].kind", "dekf", "one angle channel"),
    case("dekf-forget-zero", edit(SINE, filter=[{"kind": "dekf", "forget": 0.0}]), "filter[1].forget", "0.0", "(0, 1]"),
    case("dekf-cv-model", edit(SINE, filter=[{"kind": "dekf", "model": "cv"}]), "filter[1].model", "cv", "ca state"),
    case("dekf-scale-length", edit(SINE, filter=[{"kind": "dekf", "scale": [1.0, 2.0]}]), "filter[1].scale", "[1.0, 2.0]",
         "3 values"),
    case("sine-negative-omega", edit(SINE, scenario={"kind": "sine", "omega": -0.6}), "scenario.omega", "-0.6", "> 0"),
    # --- airborne-radar experiments ----------------------------------------------------------------
    case("airborne-unknown-tracker", edit(AIRBORNE, tracker=[{"kind": "imm"}]), "tracker[1].kind", "imm", "cd_ekf"),
    case("airborne-moose-one-level", edit(AIRBORNE, tracker=[{"kind": "moose", "levels": [0.0]}]), "tracker[1].levels",
         "[0.0]", "2-21 distinct"),
    case("airborne-moose-p-stay-1", edit(AIRBORNE, tracker=[{"kind": "moose", "p_stay": 1.0}]), "tracker[1].p_stay",
         "1.0", "(0, 1)"),
    case("airborne-no-tracker", edit(AIRBORNE, drop=["tracker"]), "[tracker]", "(missing)", "required"),
    case("airborne-lam-zero", edit(AIRBORNE, tracker=[{"kind": "cd_ekf", "lam": 0.0}]), "tracker[1].lam", "0.0", "(0, 1000]"),
    case("airborne-duplicate-label", edit(AIRBORNE, tracker=[{"kind": "cd_ekf"}, {"kind": "cd_ekf"}]), "tracker[2].label",
         "cd_ekf", "unique"),
    case("airborne-range-velocity", edit(AIRBORNE, tracker=[{"kind": "decoupled", "range_velocity": "joint"}]),
         "tracker[1].range_velocity", "joint", "coupled, separate"),
    case("airborne-classical-lam", edit(AIRBORNE, tracker=[{"kind": "classical", "lam": 3.0}]), "tracker[1].lam", "3.0",
         "unknown field"),
    case("airborne-q-scale-negative", edit(AIRBORNE, tracker=[{"kind": "cd_ekf", "q_scale": -100.0}]),
         "tracker[1].q_scale", "-100.0", "> 0"),
    case("airborne-duration-short", edit(AIRBORNE, airborne__duration=0.05), "airborne.duration", "0.05", "two filter periods"),
    case("airborne-turn-direction", edit(AIRBORNE, engagement={"turn_direction": 0.5}), "engagement.turn_direction", "0.5",
         "1 (left) or -1"),
    case("airborne-collision", edit(AIRBORNE, engagement={"target_offset": 0.0, "target_height": 0.0, "turn_g": 0.0},
                                    airborne__duration=60.0), "[engagement]", "m", "above 100 m"),
    case("airborne-gains-length", edit(AIRBORNE, noise={"gains": [1.0, 1.0]}), "noise.gains", "[1.0, 1.0]", "4 positive"),
    case("airborne-acquisition-outside-beam", edit(AIRBORNE, acquisition={"pointing": 40.0}), "acquisition.pointing", "40.0",
         "beam half-width"),
    case("airborne-disturbance-late", edit(AIRBORNE, disturbance={"time": 5.0, "pointing": 10.0}), "disturbance.time", "5.0",
         "within the run"),
    case("airborne-window-outside", to_toml(AIRBORNE) + "\n[report.windows]\nlate = [1.0, 9.0]\n", "report.windows.late",
         "[1.0, 9.0]", "t1 <= 2"),
    case("airborne-unknown-section", edit(AIRBORNE, sensor={"kind": "polar"}), "[sensor]", "...", "airborne experiment"),
    case("airborne-singer-not-bool", edit(AIRBORNE, engagement={"singer": "yes"}), "engagement.singer", "yes", "true or false"),
    # --- imm ---------------------------------------------------------------------------------------
    case("imm-unknown-model", plus_filter(kind="imm", models=["cv", "singer"]), "filter[2].models", "['cv', 'singer']",
         "cv, ca, ct"),
    case("imm-model-twice", plus_filter(kind="imm", models=["cv", "cv"]), "filter[2].models", "['cv', 'cv']", "distinct"),
    case("imm-q-per-model", plus_filter(kind="imm", models=["cv", "ct"], q=[1.0]), "filter[2].q", "[1.0]", "one per model"),
    case("imm-q-negative", plus_filter(kind="imm", models=["cv", "ct"], q=[1.0, -1.0]), "filter[2].q", "[1.0, -1.0]", "> 0"),
    case("imm-transition-rows", plus_filter(kind="imm", models=["cv", "ct"], transition=[[0.9, 0.2], [0.1, 0.9]]),
         "filter[2].transition", "[[0.9, 0.2], [0.1, 0.9]]", "rows sum to 1"),
    case("imm-p-stay-1", plus_filter(kind="imm", models=["cv", "ct"], p_stay=1.0), "filter[2].p_stay", "1.0", "(0, 1)"),
    case("imm-with-model-field", plus_filter(kind="imm", model="cv"), "filter[2].model", "cv", "its own models"),
    case("imm-ct-on-1d", edit(TRAJ, scenario={"kind": "constant_velocity", "initial": [0.0, 1.0]},
                              filter=[{"kind": "imm", "models": ["cv", "ct"]}]), "filter[1].models", "['cv', 'ct']", "2-D or 3-D"),
    # --- [[study]] tables: tuning and sweeps that reproduce rebuilds ----------------------------
    case("study-unknown-kind", edit(study=[{"kind": "grid", "out": "x"}]), "study[1].kind", "grid", "tune, sweep"),
    case("study-out-escapes", edit(study=[{"kind": "sweep", "grid": ["q=0.1:10:3"], "out": "../elsewhere"}]),
         "study[1].out", "../elsewhere", "relative folder"),
    case("study-out-absolute", edit(study=[{"kind": "sweep", "grid": ["q=0.1:10:3"], "out": "/tmp/x"}]),
         "study[1].out", "/tmp/x", "relative folder"),
    case("study-tune-unknown-param", edit(study=[{"kind": "tune", "params": ["qq"], "out": "t"}]), "study[1].params",
         "['qq']", "among"),
    case("study-tune-unknown-filter", edit(study=[{"kind": "tune", "params": ["q"], "filters": ["KF"], "out": "t"}]),
         "study[1].filters", "['KF']", "EKF"),
    case("study-tune-param-no-filter-has", edit(study=[{"kind": "tune", "params": ["rho"], "out": "t"}]),
         "study[1].params", "['rho']", "parameters among q, r"),
    case("study-tune-zero-lr", edit(study=[{"kind": "tune", "params": ["q"], "lr": 0.0, "out": "t"}]), "study[1].lr",
         "0.0", "> 0"),
    case("study-sweep-bad-grid", edit(study=[{"kind": "sweep", "grid": ["q=1:0.1:3"], "out": "s"}]), "study[1].grid",
         "q=1:0.1:3", "LO <= HI"),
    case("study-sweep-twice-q", edit(study=[{"kind": "sweep", "grid": ["q=0.1:1:2", "q=1:10:2"], "out": "s"}]),
         "study[1].grid", "q=0.1:1:2", "once"),
    case("study-same-out-twice", edit(study=[{"kind": "sweep", "grid": ["q=0.1:1:2"], "out": "s"},
                                             {"kind": "sweep", "grid": ["r=0.1:1:2"], "out": "s"}]), "study[2].out", "s",
         "unique"),
    case("study-unknown-field", edit(study=[{"kind": "sweep", "grid": ["q=0.1:1:2"], "out": "s", "runz": 3}]),
         "study[1].runz", "3", "unknown field"),
    # --- huge but finite values ----------------------------------------------------------------
    case("sigma-1e200", edit(sensor__sigma_r=1e200), "sensor.sigma_r", "1e+200"),
    case("filter-accel-sigma-1e200", edit(filter1__accel_sigma=1e200), "filter[1].accel_sigma", "1e+200"),
    case("prior-pos-sigma-1e200", edit(prior__pos_sigma=1e200), "prior.pos_sigma", "1e+200"),
    case("dt-1e200", edit(experiment__dt=1e200), "experiment.dt", "1e+200"),
    case("trajectory-dt-denormal", traj(experiment__dt=5e-324), "experiment.dt", "5e-324"),
]


def _write(tmp_path, spec):
    csv_text = None
    if isinstance(spec, dict) and "cfg" in spec:
        spec, csv_text = spec["cfg"], spec["csv"]
    if isinstance(spec, dict):
        spec = to_toml(spec)
    path = tmp_path / FILE
    if isinstance(spec, bytes):
        path.write_bytes(spec)
    else:
        path.write_text(spec)
    if csv_text is not None:
        p = tmp_path / CSV
        p.write_bytes(csv_text) if isinstance(csv_text, bytes) else p.write_text(csv_text)
    return path


def _check(err: ConfigError, field, value, more):
    msg = str(err)
    assert "\n" not in msg and "\r" not in msg, f"message is not one line: {msg!r}"
    assert FILE in msg, msg
    assert err.field == field, msg
    assert field in msg, msg
    assert value in msg, msg
    for s in more:
        assert s in msg, f"{s!r} not in {msg!r}"
    assert err.allowed and err.allowed.strip(), "the message must say what is allowed"


@pytest.mark.parametrize("spec, field, value, more", CASES)
def test_broken_file_is_refused(tmp_path, spec, field, value, more):
    path = _write(tmp_path, spec)
    with pytest.raises(ConfigError) as info:
        load_experiment(path)
    _check(info.value, field, value, more)


def test_missing_experiment_file(tmp_path):
    path = tmp_path / "nope" / "absent.toml"
    with pytest.raises(ConfigError) as info:
        load_experiment(path)
    msg = str(info.value)
    assert "\n" not in msg
    assert "absent.toml" in msg and "does not exist" in msg
    assert info.value.field == "file"


def test_experiment_path_is_a_folder(tmp_path):
    with pytest.raises(ConfigError) as info:
        load_experiment(tmp_path)
    assert info.value.field == "file" and str(tmp_path) in str(info.value)


def test_config_error_is_a_value_error():
    assert issubclass(ConfigError, ValueError)


# --- the base files themselves are valid (so every case above breaks exactly one thing) ----------


def test_base_config_is_valid(tmp_path):
    exp = load_experiment(_write(tmp_path, BASE))
    assert (exp.name, exp.runs, exp.steps, exp.dim) == ("small", 20, 10, 2)
    assert [f.kind for f in exp.filters] == ["ekf"]
    assert exp.window == (1, 10)


def test_base_trajectory_config_is_valid(tmp_path):
    exp = load_experiment(_write(tmp_path, {"cfg": TRAJ, "csv": GOOD_CSV}))
    assert exp.dim == 3 and exp.sensor.kind == "cartesian"
    assert exp.scenario.max_steps() == 20
    assert exp.scenario.truth().shape == (11, 6)


@pytest.mark.parametrize(
    "cfg",
    [
        pytest.param(edit(scenario__altitude=3000.0, sensor={"kind": "spherical", "sigma_r": 100.0,
                                                             "sigma_az": 0.003, "sigma_el": 0.003},
                          filter=[{"kind": "cmkf", "debias": "unbiased"}, {"kind": "sequential_ekf"}]),
                     id="spherical-3d"),
        pytest.param(edit(filter=[{"kind": "cmkf", "debias": "additive"}, {"kind": "polar_kf"}]), id="polar-2d"),
        pytest.param(edit(sensor={"kind": "cartesian", "sigma": [10.0, 20.0]},
                          filter=[{"kind": "kf", "sigma": 15.0}, {"kind": "ekf", "model": "ca"}]), id="cartesian-2d"),
        pytest.param(edit(report__window=[10, 10], experiment__runs=1, experiment__steps=10), id="edge-window"),
        pytest.param(edit(AIRBORNE, tracker=[{"kind": "classical"}, {"kind": "decoupled", "range_velocity": "separate"},
                                             {"kind": "moose", "levels": [-30.0, 0.0, 30.0], "p_stay": 0.9}],
                          engagement={"turn_direction": -1.0, "turn_g": 0.0}, disturbance={"time": 1.0, "pointing": -5.0}),
                     id="airborne-variants"),
    ],
)
def test_near_misses_are_accepted(tmp_path, cfg):
    """Neighbours of the broken cases that must still load (the checks are not too eager)."""
    load_experiment(_write(tmp_path, cfg))
