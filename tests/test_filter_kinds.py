"""Each filter kind is declared once (``tracklab.filters.kind``): a wrong declaration is caught here.

The declarations are what the configuration, tuning, sweeps and ``tracklab list`` read, so
these tests check them against what those do: documented and constrained parameters,
tune's unconstrained coordinates, the defaults a minimal file gives, unknown fields refused.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import tracklab.filters
from tracklab import cli
from tracklab.config import load_experiment
from tracklab.worlds.tracking.experiment import Experiment
from tracklab.errors import ConfigError
from tracklab.parameters import Constraint, Param
from tracklab.filters.registry import KINDS, SCALABLE, TUNABLE, declarations
from tracklab.sensors import SENSORS
from tracklab.studies.tune import decode, encode

TUNED = [k for k in KINDS.values() if any(p.tune for p in k.params.values())]


def test_every_kind_declares_a_doc_the_sensors_it_accepts_and_constrained_parameters():
    assert list(KINDS) and all(name == k.name for name, k in KINDS.items())
    for k in KINDS.values():
        assert k.doc.strip() and "\n" not in k.doc, k.name
        assert k.accepts and set(k.accepts) <= set(SENSORS) | {"suite", "custom"}, k.name
        assert k.params and callable(k.read) and callable(k.build), k.name
        for name, p in k.params.items():
            assert isinstance(p, Param) and isinstance(p.constraint, Constraint), (k.name, name)
            assert p.doc.strip(), (k.name, name)
            assert not p.tune or p.constraint.tunable, (k.name, name)
            assert not p.sweep or p.constraint.scalable, (k.name, name)
            if p.default is not None:
                assert p.constraint.contains({name: p.default}), (k.name, name)


def test_a_parameter_name_means_the_same_in_every_kind():
    """`tracklab tune --params q` and `sweep --grid q=…` name a parameter across kinds: the same
    constraint and scale-factor sweep everywhere; tunable everywhere but in the associations that
    choose one return (nn, snf), whose hard choice has no gradient."""
    hard = {"nn", "snf"}
    for name in {n for k in KINDS.values() for n in k.params}:
        ps = declarations(name)
        assert len({(p.constraint, p.sweep) for p in ps}) == 1, name
        assert len({k.params[name].tune for k in KINDS.values() if name in k.params and k.name not in hard}) == 1, name
    assert not any(p.tune for k in hard for p in KINDS[k].params.values())


def test_what_tune_and_sweep_accept():
    assert set(TUNABLE) == {"q", "r", "lam", "b", "q_e", "r_e", "r_guide", "pw0", "rho", "forget", "w0", "alpha", "beta",
                            "gamma", "gate", "p_detect", "clutter_density", "p_survive", "existence0"}
    assert set(SCALABLE) == {"q", "r", "lam", "alpha", "beta", "gamma", "rho", "b", "q_e", "r_e", "r_guide",
                             "clutter_density"}


def _inside(name, p: Param, rng):
    """A value of the declared parameter inside its constraint."""
    if p.default is not None:
        return np.asarray(p.default, float)
    if name in ("alpha", "beta", "gamma"):
        return np.asarray({"alpha": 0.5, "beta": 0.3, "gamma": 0.05}[name])
    if p.constraint.bounds == "(-inf, inf)":
        return rng.normal(size=5)
    return rng.uniform(0.2, 0.9, size=2)  # positive or in (0, 1]


@pytest.mark.parametrize("kind", TUNED, ids=lambda k: k.name)
def test_tune_round_trips_every_declared_parameter(kind):
    rng = np.random.default_rng(0)
    params = {n: _inside(n, p, rng) for n, p in kind.params.items()}
    for name, p in kind.params.items():
        if not p.tune:
            continue
        theta = encode({name: p.constraint}, params)
        assert name in theta
        back = decode({name: p.constraint}, theta)
        for n in theta:  # jointly constrained parameters come back together
            np.testing.assert_allclose(np.asarray(back[n]), params[n], rtol=1e-9, err_msg=f"{kind.name}.{n}")


@pytest.mark.parametrize("kind", TUNED, ids=lambda k: k.name)
def test_decode_lands_inside_the_constraint(kind):
    rng = np.random.default_rng(1)
    params = {n: _inside(n, p, rng) for n, p in kind.params.items()}
    for name, p in kind.params.items():
        if not p.tune:
            continue
        for _ in range(20):
            theta = {n: rng.normal(scale=5.0, size=np.shape(u)) for n, u in encode({name: p.constraint}, params).items()}
            out = decode({name: p.constraint}, theta)
            assert p.constraint.contains({n: np.asarray(out[n]) for n in theta}), (kind.name, name, theta)


def test_list_names_every_kind_its_sensors_and_parameters(tmp_path, capsys):
    assert cli.main(["list", "--dir", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    words = out.replace(",", " ").split()
    for k in KINDS.values():
        assert k.name in words and k.doc in out, k.name
        assert all(n in words for n in k.params), k.name


def _minimal(kind) -> str:
    """The smallest experiment file with one filter of ``kind`` and no field of its own."""
    if kind.name == "dekf":  # one angle channel
        world = '[scenario]\nkind = "sine"\n\n[sensor]\nkind = "cartesian"\nsigma = 0.003\n'
    elif "cartesian" in kind.accepts:
        world = ('[scenario]\nkind = "constant_velocity"\ninitial = [0.0, 10.0, 1000.0, -5.0]\naccel_sigma = 0.5\n\n'
                 '[sensor]\nkind = "cartesian"\nsigma = 10.0\n')
        if kind.scans:  # an association: a cluttered sensor and the track-loss test
            world += ('clutter_density = 1e-4\nclutter_window = [100.0, 100.0]\n' + ('snr = 10.0\n' if kind.name == "snf" else '')
                      + '\n[track_loss]\ndistance = 50.0\n')  # the strongest neighbour: amplitudes

    else:
        world = '[scenario]\nkind = "crossing"\n\n[sensor]\nkind = "polar"\nsigma_r = 100.0\nsigma_angle = 0.003\n'
    return (f'[experiment]\nname = "minimal"\nruns = 2\ndt = 0.5\nsteps = 10\n\n{world}\n'
            f'[[filter]]\nkind = "{kind.name}"\n')


@pytest.mark.parametrize("kind", KINDS.values(), ids=lambda k: k.name)
def test_declared_defaults_are_what_a_minimal_file_gives(tmp_path, kind):
    path = tmp_path / "minimal.toml"
    path.write_text(_minimal(kind))
    fc = load_experiment(path).filters[0]
    assert set(fc.params) <= set(kind.params), "a parameter the kind does not declare"
    assert not any(isinstance(v, float) for v in fc.options.values()), "a number among the options"
    for name, p in kind.params.items():
        if p.default is not None:
            assert np.asarray(fc.params[name], float).tolist() == np.asarray(p.default, float).tolist(), name


@pytest.mark.parametrize("kind", KINDS.values(), ids=lambda k: k.name)
def test_an_unknown_field_in_a_filter_entry_is_refused_in_one_line(tmp_path, kind):
    path = tmp_path / "typo.toml"
    path.write_text(_minimal(kind) + "acel_sigma = 1.0\n")
    with pytest.raises(ConfigError) as info:
        load_experiment(path)
    msg = str(info.value)
    assert "\n" not in msg and "typo.toml" in msg and "unknown field" in msg, msg
    assert info.value.field == "filter[1].acel_sigma"


def test_numbers_are_parameters_and_options_are_hashable_structure():
    """Every number of a [[filter]] table is an input of the compiled program (params); the options,
    a static key of the program, are strings, booleans, integer sizes and tuples of them."""

    def structural(v):
        if isinstance(v, tuple):
            return all(structural(x) for x in v)
        return isinstance(v, (str, bool, int))

    files = sorted((Path(__file__).parent.parent / "experiments").glob("*.toml"))
    for f in files:
        exp = load_experiment(f)
        if not isinstance(exp, Experiment):
            continue
        for fc in exp.filters:
            if fc.kind not in KINDS:  # a filter of one's own (experiments/own_filter.toml): its numbers are its params
                continue
            hash(tuple(sorted(fc.options.items())))
            assert all(structural(v) for v in fc.options.values()), (f.name, fc.label, fc.options)
            assert set(fc.params) <= set(KINDS[fc.kind].params), (f.name, fc.label)
