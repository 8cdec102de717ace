"""tracklab.random draws the values of jax.random, and any part of a draw on its own."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tracklab import random

KEYS = [jax.random.key(0), jax.random.fold_in(jax.random.key(7), 123456), jax.random.key(2**31 + 5)]


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
@pytest.mark.parametrize("shape", [(1,), (7,), (200, 2), (3, 4, 5)])
def test_standard_normal_is_jax_random_normal_to_the_bit(dtype, shape):
    for key in KEYS:
        ours = jax.jit(random.standard_normal, static_argnums=(1, 2))(key, shape, dtype)
        theirs = jax.random.normal(key, shape, dtype)
        assert ours.dtype == theirs.dtype
        np.testing.assert_array_equal(np.asarray(ours), np.asarray(theirs))


@pytest.mark.parametrize("width", [32, 64])
def test_bits_and_uniform_are_jax_randoms(width):
    for key in KEYS:
        np.testing.assert_array_equal(np.asarray(random.bits(key, (50, 3), width)),
                                      np.asarray(jax.random.bits(key, (50, 3), np.dtype(f"uint{width}"))))
        np.testing.assert_array_equal(np.asarray(random.uniform(key, (50, 3))),
                                      np.asarray(jax.random.uniform(key, (50, 3), jnp.float32)))


def test_a_row_drawn_alone_is_that_row_of_the_whole_draw_also_under_vmap():
    T, m = 40, 3
    keys = jax.random.split(jax.random.key(3), 5)
    whole = jax.vmap(lambda k: random.normal(k, (T, m), jnp.float64))(keys)
    rows = jax.vmap(lambda k: jax.vmap(lambda r: random.normal(k, (m,), jnp.float64, offset=r * m))(jnp.arange(T)))(keys)
    np.testing.assert_array_equal(np.asarray(rows), np.asarray(whole))
    # the simulation's draws are jax's float32 normals, cast
    np.testing.assert_array_equal(np.asarray(whole[2]),
                                  np.asarray(jax.random.normal(keys[2], (T, m), jnp.float32), np.float64))


def test_normal_draws_are_standard_normal():
    z = np.asarray(random.normal(jax.random.key(11), (200_000,), jnp.float64))
    assert abs(z.mean()) < 5 / np.sqrt(z.size)
    assert abs(z.var() - 1.0) < 5 * np.sqrt(2.0 / z.size)
    assert abs(np.mean(z**4) - 3.0) < 0.05  # Gaussian kurtosis
