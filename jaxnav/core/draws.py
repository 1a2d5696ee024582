"""Many small random draws from few hashes: `Draws` hands out uniform numbers of one key in order,
from blocks that one `jax.random.uniform` call draws each.

A room sampler draws dozens of small values (sizes, counts, poses, the robot's parameters). With a
key per value, each is a threefry hash of its own, and on a GPU JAX inlines every hash as ~130
unrolled ops, which XLA copies into the fusions that read them. From a `Draws`, a reset costs a
few hashes: lowered for CUDA, the `avoid` reset has 44 % fewer ops (docs/results.md, "What
was decided and why").
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp

BLOCK = 64  # uniform numbers per block; a larger request draws a block of its own size
SALT = 2**31  # block i's key is fold_in(key, SALT + i): apart from small numbers folded into key


class Draws:
    """Uniform numbers in [0, 1) of `key`, handed out in order.

    Pure: the same key and the same requests in the same order give the same numbers, and
    numbers handed out once are never handed out again. A `Draws` lives at one level of tracing:
    a `lax.cond`/`switch`/`scan`/`fori_loop` body must not take numbers from one made outside it
    (its block would leak); give the body `draws.key()` and a `Draws` of its own.
    """

    def __init__(self, key: jax.Array, block: int = BLOCK):
        self._key = key
        self._block = block
        self._pool = None  # [block] the current block
        self._used = 0  # numbers of the current block handed out
        self._blocks = 0  # blocks and keys drawn so far

    def _next_key(self) -> jax.Array:
        self._blocks += 1
        return jax.random.fold_in(self._key, SALT + self._blocks)

    def _take(self, n: int) -> jax.Array:
        """[n] fresh uniform numbers."""
        if n > self._block:
            return jax.random.uniform(self._next_key(), (n,))
        if self._pool is None or self._used + n > self._block:
            self._pool, self._used = jax.random.uniform(self._next_key(), (self._block,)), 0
        out = self._pool[self._used : self._used + n]
        self._used += n
        return out

    def key(self) -> jax.Array:
        """A key of its own (for a control-flow body, or a draw that needs a key)."""
        return self._next_key()

    def uniform(self, shape=(), minval=0.0, maxval=1.0) -> jax.Array:
        """[shape] float32 uniform in [minval, maxval) (bounds broadcast against shape)."""
        u = self._take(math.prod(shape)).reshape(shape)
        return minval + u * (jnp.asarray(maxval) - minval)

    def randint(self, shape, minval, maxval) -> jax.Array:
        """[shape] int32 uniform in {minval, ..., maxval - 1} (traced bounds allowed)."""
        lo, hi = jnp.asarray(minval, jnp.int32), jnp.asarray(maxval, jnp.int32)
        span = jnp.maximum(hi - lo, 1)
        pick = jnp.floor(self.uniform(shape) * span).astype(jnp.int32)
        return lo + jnp.minimum(pick, span - 1)

    def bernoulli(self, p=0.5, shape=()) -> jax.Array:
        """[shape] bool, True with probability p."""
        return self.uniform(shape) < p

    def normal(self, shape=()) -> jax.Array:
        """[shape] float32 standard normal."""
        return normal_of(self.uniform(shape))

    def choice(self, p: jax.Array) -> jax.Array:
        """int32 index i with probability p[i] / sum(p)."""
        cdf = jnp.cumsum(p)
        i = jnp.searchsorted(cdf, self.uniform() * cdf[-1], side="right")
        return jnp.minimum(i, p.shape[0] - 1).astype(jnp.int32)


def _mix(x: jax.Array) -> jax.Array:
    """[...] uint32 each word mixed by a bijective 32-bit hash (two xorshift-multiply rounds)."""
    x = (x ^ (x >> 16)) * jnp.uint32(0x7FEB352D)
    x = (x ^ (x >> 15)) * jnp.uint32(0x846CA68B)
    return x ^ (x >> 16)


def hashed_uniform(key: jax.Array, shape: tuple[int, ...]) -> jax.Array:
    """[shape] float32 uniform in [0, 1) of `key`: each value's index hashed with the key's two
    words (`_mix`, twice), 24 bits a value. For noise drawn anew every step (the camera's), where
    jax.random.uniform's threefry (20 rounds for every two values; on the CPU a rolled loop)
    costs a 512-robot step ten times as long (`benchmarks/camera_noise.py`); its statistics:
    tests/test_draws.py. A typed key or a raw uint32[2] one."""
    if jax.dtypes.issubdtype(key.dtype, jax.dtypes.prng_key):
        key = jax.random.key_data(key)
    words = key.reshape(-1).astype(jnp.uint32)
    index = jnp.arange(math.prod(shape), dtype=jnp.uint32).reshape(shape)
    bits = _mix(_mix(index ^ words[0]) + words[1])
    return (bits >> 8).astype(jnp.float32) * jnp.float32(2.0**-24)


FEISTEL_ROUNDS = 4  # rounds of `hashed_permutation`'s cipher (Luby-Rackoff's count for a PRP)


def hashed_permutation(key: jax.Array, n: int) -> jax.Array:
    """[n] int32: a permutation of 0..n-1 of `key`, without sorting and without a loop. Every
    index of the cipher's domain (the fewest even number of bits covering n, so up to 4n
    indices) is enciphered by a balanced Feistel network (`FEISTEL_ROUNDS` rounds, each mixing one
    half with a round's key word by `_mix`), a one-to-one map of the domain; the images below n,
    kept in the order of their indices (a prefix sum places each), are the permutation. For the
    learner's minibatches: jax.random.permutation sorts twice by random keys, 8 radix-sort passes
    an epoch on a GPU and a comparison sort on the CPU, and walking the cipher's cycles instead
    loops with the GPU waiting on the host at each turn (docs/results.md, "What was decided and
    why"); statistics: tests/test_draws.py."""
    if n <= 1:
        return jnp.arange(n, dtype=jnp.int32)
    half = ((n - 1).bit_length() + 1) // 2  # bits of each half: 2 * half >= bits of n - 1
    mask = jnp.uint32((1 << half) - 1)
    words = jax.random.bits(key, (FEISTEL_ROUNDS,), jnp.uint32)
    index = jnp.arange(1 << (2 * half), dtype=jnp.uint32)  # [D], D = 2^(2 half) in [n, 4n)
    left, right = index >> half, index & mask
    for i in range(FEISTEL_ROUNDS):
        left, right = right, left ^ (_mix(right ^ words[i]) & mask)
    x = ((left << half) | right).astype(jnp.int32)  # [D]: a permutation of 0..D-1
    if x.shape[0] == n:
        return x
    below = x < n
    place = jnp.where(below, jnp.cumsum(below, dtype=jnp.int32) - 1, n)  # [D]: n drops
    return jnp.zeros(n, jnp.int32).at[place].set(x, mode="drop", unique_indices=True)


def normal_of(u: jax.Array) -> jax.Array:
    """[...] standard normal values of uniform ones in [0, 1) (the inverse CDF, as jax.random
    draws them)."""
    return jnp.sqrt(2.0) * jax.lax.erf_inv(2.0 * u - 1.0 + 2.0**-24)  # erf_inv of (-1, 1)


def draws(source: jax.Array | Draws) -> Draws:
    """`source` itself if it is a `Draws`, else a `Draws` of the key."""
    return source if isinstance(source, Draws) else Draws(source)
