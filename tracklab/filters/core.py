"""The filter contract: what a filter is, what it receives and what it reports.

A filter is a small immutable bundle of pure functions over pytrees, in the
spirit of optax's ``GradientTransformation``::

    state = flt.init(params, prior)
    state, out = flt.step(params, state, meas)

``flt.params`` holds the default parameters (a pytree of arrays: what
``jax.grad`` and optax see). Static structure (dimensions, model choice) lives
in the closures. The Gaussian predict/update algebra to write one with is ``blocks``.
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp

from tracklab.errors import failure


class Prior(NamedTuple):
    """Gaussian prior one sample period before the first measurement."""

    x: jax.Array
    P: jax.Array


class Meas(NamedTuple):
    """One measurement: value, time and validity.

    An absent component (a missed detection, a sensor with no report at this step) is NaN in
    ``z``; ``valid`` is True whenever the step is run with a measurement vector (the engine and
    ``run_filter`` always pass True), so a filter tells what is there from ``z``'s finite
    components (``masked_meas``) or from ``present``.

    ``present`` (optional, one flag per component) says which components are
    there when that is known without looking at ``z``: the engine passes the
    sensors' report pattern when every sensor detects with probability one, so
    under ``vmap`` it is shared by all runs, and so is everything a filter computes
    from it alone (a linear KF's covariance and gain: once per step, not once per run).
    By default the components that are present are the finite ones.
    """

    z: jax.Array
    t: jax.Array
    valid: jax.Array
    present: jax.Array | None = None


class Out(NamedTuple):
    """What a filter reports after each step.

    Required: ``x``/``P``, the filtered mean and covariance of the filter's state (the
    engine reads position and velocity through the filter's ``layout``). Optional (None:
    the statistics that need them are empty, never wrong):

    * ``x_pred``: the one-step prediction of the state, made before this step's
      measurement (the one-step prediction error);
    * ``nu``/``S``: the innovation and its covariance in the filter's measurement space
      (NIS); components not used are zero in ``nu`` and decoupled with unit variance in ``S``;
    * ``valid``: whether an update happened (default: True when ``nu`` is given);
    * ``dof``: how many innovation components it used (default: the length of ``nu``);
    * ``aux``: what a filter family adds (the strong tracking filter's fading factor, an
      IMM's mode probabilities);
    * ``validated``: a filter of scans (``association``): how many returns it validated (NaN at
      a step with no scan).
    """

    x: jax.Array
    P: jax.Array
    x_pred: jax.Array | None = None
    nu: jax.Array | None = None
    S: jax.Array | None = None
    valid: jax.Array | None = None
    dof: jax.Array | None = None
    aux: Any = None
    validated: jax.Array | None = None


class Filter(NamedTuple):
    """A filter: ``init(params, prior) -> state`` and ``step(params, state, meas) -> (state, Out)``.

    ``params`` is the default parameter pytree (what ``jax.grad`` and optax see). ``coast``
    (optional) is the step when no measurement is present, equal to ``step`` with an absent
    measurement but cheaper. ``layout`` (optional, a ``tracklab.models.Layout``) says where
    position and velocity sit in the state; None: the interleaved layout [x, ẋ, y, ẏ(, z, ż)].
    The prior handed to ``init`` is in that layout (other state components: zero mean,
    the experiment's extra prior variance). ``declared`` (set by ``tracklab.declare``): the
    numbers of ``params`` its factory declares, name -> ``Param``.
    """

    init: Callable[[Any, Prior], Any]
    step: Callable[[Any, Any, Meas], tuple[Any, Out]]
    params: Any
    coast: Callable[[Any, Any, Meas], tuple[Any, Out]] | None = None
    layout: Any = None
    declared: Any = None


def select(valid, a, b):
    """Pytree-wise ``where(valid, a, b)`` (a missed detection keeps ``b``)."""
    return jax.tree_util.tree_map(lambda u, v: jnp.where(valid, u, v), a, b)


def measuring(flt: Filter, m: int) -> Filter:
    """``flt``, built for measurements of ``m`` components, refusing any other size when traced
    (``ValueError``): its arrays might otherwise broadcast with a z of another size, or index
    past its end, and run on NaN."""

    def checked(fn):
        def step(params, state, meas):
            if jnp.shape(meas.z) != (m,):
                raise ValueError(f"the filter measures {m} components, z has shape {jnp.shape(meas.z)}")
            return fn(params, state, meas)

        return step

    return flt._replace(step=checked(flt.step), coast=None if flt.coast is None else checked(flt.coast))


def masked_meas(meas: Meas):
    """Measurement with NaNs replaced by zeros, and which components are present."""
    present = meas.valid & (jnp.isfinite(meas.z) if meas.present is None else meas.present)
    return jnp.where(present, meas.z, 0.0), present


def trace_problem(flt: Filter, n: int, m: int, params=None, precision: str = "float64", *,
                  outputs: bool = True, returns: int | None = None) -> str | None:
    """Why ``flt`` cannot run on a state of ``n`` and measurements of ``m`` components (None if it
    can): ``init`` and ``step`` traced on shapes alone (nothing compiles), their outputs checked
    against the contract (``Out`` with x (n,), P (n, n), optional x_pred (n,), nu (k,) with
    S (k, k); a state of the same structure and shapes as ``init``'s). Traced in the
    ``precision`` the filter will run in (JAX keeps what it traced in one mode for the other).
    ``returns``: a cluttered sensor's scans, z of shape (returns, m) (a filter of scans).
    ``outputs=False``: only that it traces, keeps its state's shapes and gives nu (k,) with S
    (k, k) if either (``run_filter``, which reports x and P in whatever shapes the filter gives)."""
    params = flt.params if params is None else params
    dtype = jnp.float64 if precision == "float64" else jnp.float32
    f64 = lambda *shape: jax.ShapeDtypeStruct(shape, dtype)  # noqa: E731
    try:
        with jax.enable_x64(precision == "float64"):
            params = jax.tree_util.tree_map(
                lambda a: jnp.asarray(a, dtype) if jnp.issubdtype(jnp.result_type(a), jnp.floating) else a, params)
            state = jax.eval_shape(flt.init, params, Prior(f64(n), f64(n, n)))
            z = f64(m) if returns is None else f64(returns, m)
            state2, out = jax.eval_shape(flt.step, params, state, Meas(z, f64(), jax.ShapeDtypeStruct((), bool)))
    except BaseException as e:  # noqa: BLE001 - the user's functions: any error, a sys.exit too
        if isinstance(e, KeyboardInterrupt):
            raise
        what = f"a measurement of {m} components" if returns is None else f"a scan of {returns} returns of {m} components"
        hint = (" (a cluttered sensor's scans need a filter of scans: tracklab.filters.pdaf(your filter, m, …), "
                "nearest_neighbour or ipda)") if returns is not None else ""
        return f"fails when traced with a state of {n} and {what}: {failure(e)}{hint}"
    if not isinstance(out, Out):
        return f"step returns {type(out).__name__} as its output: expected tracklab.filters.Out(x, P, …)"
    shapes = lambda t: jax.tree_util.tree_map(lambda a: a.shape, t)  # noqa: E731
    if jax.tree_util.tree_structure(state2) != jax.tree_util.tree_structure(state) or shapes(state2) != shapes(state):
        return f"step returns a state shaped {shapes(state2)}, init gives {shapes(state)}: they must be alike"
    shape = lambda a: getattr(a, "shape", None)  # noqa: E731
    if (out.nu is None) != (out.S is None):
        return "step gives only one of nu and S: give both (NIS) or neither"
    if out.nu is not None and (len(shape(out.nu) or ()) != 1 or shape(out.S) != shape(out.nu) * 2):
        return f"step gives nu {shape(out.nu)} and S {shape(out.S)}: expected (k,) and (k, k)"
    if not outputs:
        return None
    if shape(out.x) != (n,) or shape(out.P) != (n, n):
        return (f"step gives x {shape(out.x)} and P {shape(out.P)}, the layout has n = {n}: "
                f"expected ({n},) and ({n}, {n}) (set Filter.layout for another state order)")
    if out.x_pred is not None and shape(out.x_pred) != (n,):
        return f"step gives x_pred {shape(out.x_pred)}: expected ({n},)"
    return None


def measurement_sizes(flt: Filter, n: int, sizes, params=None, precision: str = "float64", *,
                      outputs: bool = True) -> list[int]:
    """The measurement sizes among ``sizes`` that ``flt`` runs with on a state of ``n`` (those
    ``trace_problem`` finds nothing wrong with): what a filter measures, found by tracing alone."""
    return [m for m in sizes if trace_problem(flt, n, m, params, precision, outputs=outputs) is None]
