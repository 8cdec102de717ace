"""The Monte-Carlo simulation's random draws: JAX's threefry values, computed faster on the CPU.

``jax.random.normal(key, shape, dtype)`` with the default threefry-2x32 key and
partitionable bits (``jax_threefry_partitionable``, on by default) hashes the
element's linear index n as the counter pair (n >> 32, n mod 2³²) with the key
(Salmon et al., "Parallel random numbers: as easy as 1, 2, 3", 2011: 20 rounds),
takes 64 bits (x₀ << 32 | x₁) or 32 bits (x₀ ^ x₁), fills the mantissa of a
float in [1, 2), maps it to [nextafter(−1, 0), 1) and returns √2 · erfinv(u).

On the CPU, JAX lowers the 20 rounds as a rolled loop of five iterations, each a
separate pass over the whole array. ``standard_normal`` and ``uniform`` write the
same rounds out, so XLA fuses hash, float conversion and erfinv into one loop over
the elements: the same values to the bit (tested against ``jax.random``), about
eight times faster in float32. Because the hash is counter-based, any run of
elements can be drawn on its own (``offset``).

``normal`` is what the simulation uses: float32 draws (erfinv in float64 costs
eight times float32's), cast to the experiment's precision.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

_ROTATIONS = ((13, 15, 26, 6), (17, 29, 16, 24))
_PARITY = np.uint32(0x1BD11BDA)


def _rotl(v, d):
    return (v << np.uint32(d)) | (v >> np.uint32(32 - d))


def threefry2x32(k0, k1, x0, x1):
    """Threefry-2x32, 20 rounds, unrolled: the hash of the counter pair (x0, x1) under key (k0, k1)."""
    ks = (k0, k1, k0 ^ k1 ^ _PARITY)
    x0, x1 = x0 + ks[0], x1 + ks[1]
    for i in range(5):
        for r in _ROTATIONS[i % 2]:
            x0 = x0 + x1
            x1 = x0 ^ _rotl(x1, r)
        x0 = x0 + ks[(i + 1) % 3]
        x1 = x1 + ks[(i + 2) % 3] + np.uint32(i + 1)
    return x0, x1


def bits(key, shape, width: int, offset=0):
    """``jax.random.bits(key, (n,), uint{width})[offset:offset + size].reshape(shape)`` for a
    threefry key, width 32 or 64: the elements ``offset …`` of a longer draw, without the rest
    (``offset`` may be traced: row k of a (T, m) draw is ``bits(key, (m,), w, k * m)``)."""
    shape = tuple(int(s) for s in shape)
    size = math.prod(shape)
    if size >= 2**32:  # the counter's high word would be needed
        raise ValueError(f"at most 2**32 - 1 draws per key, asked for {size}")
    kd = jax.random.key_data(key)
    k0, k1 = kd[..., 0], kd[..., 1]
    lo = lax.iota(np.uint32, size).reshape(shape) + jnp.asarray(offset, np.uint32)
    x0, x1 = threefry2x32(k0, k1, jnp.zeros_like(lo), lo)
    if width == 64:
        return (x0.astype(np.uint64) << np.uint64(32)) | x1.astype(np.uint64)
    if width == 32:
        return x0 ^ x1
    raise ValueError(f"width must be 32 or 64, got {width}")


def uniform(key, shape, dtype=jnp.float32, offset=0):
    """The values of ``jax.random.uniform(key, shape, dtype)``: [0, 1), dtype float32 or float64
    (``offset``: as in ``bits``). The bits fill the mantissa of a float in [1, 2)."""
    dtype = np.dtype(dtype)
    finfo = np.finfo(dtype)
    nbits, nmant = finfo.bits, finfo.nmant
    uint = np.dtype(f"uint{nbits}")
    one = np.array(1.0, dtype)
    b = bits(key, shape, nbits, offset)
    return lax.bitcast_convert_type((b >> uint.type(nbits - nmant)) | one.view(uint), dtype) - one


def standard_normal(key, shape, dtype=jnp.float32, offset=0):
    """The values of ``jax.random.normal(key, shape, dtype)``, dtype float32 or float64
    (``offset``: as in ``bits``)."""
    dtype = np.dtype(dtype)
    one = np.array(1.0, dtype)
    floats = uniform(key, shape, dtype, offset)
    lo = np.nextafter(np.array(-1.0, dtype), np.array(0.0, dtype), dtype=dtype)
    u = lax.max(lo, floats * (one - lo) + lo)
    return np.array(np.sqrt(2), dtype) * lax.erf_inv(u)


def normal(key, shape, dtype=jnp.float32, offset=0):
    """The simulation's Gaussian draws: ``jax.random.normal(key, shape, float32)`` cast to ``dtype``.

    Drawn in single precision whatever ``dtype`` (on the CPU float32's erfinv is about
    eight times cheaper than float64's), so float32 and float64 experiments see the same
    realisations. Their resolution (2⁻²⁴ in probability, tails to ±5.3σ) is far below what
    the Monte-Carlo statistics can resolve.
    """
    return standard_normal(key, shape, np.float32, offset).astype(dtype)
