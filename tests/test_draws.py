"""`jaxnav.core.draws.Draws`: many small draws of one key from a few threefry calls, with the
distributions of jax.random's (moments and frequencies against their exact values)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxnav.core.draws import BLOCK, Draws, draws, hashed_permutation, hashed_uniform, normal_of

N = 20_000  # draws per statistic: standard errors about 0.2 % of a uniform's range


def _many(fn, n=N, seed=0):
    """[n, ...] of fn(Draws) over n keys."""
    keys = jax.random.split(jax.random.PRNGKey(seed), n)
    return np.asarray(jax.jit(jax.vmap(lambda k: fn(Draws(k))))(keys))


def test_the_same_key_and_requests_give_the_same_numbers_never_twice():
    key = jax.random.PRNGKey(3)

    def take(d):
        # small requests fill blocks; one larger than a block gets its own
        return jnp.concatenate([d.uniform((5,)), d.uniform((BLOCK - 3,)), d.uniform((2 * BLOCK,))])

    a, b = take(Draws(key)), take(Draws(key))
    np.testing.assert_array_equal(a, b)
    assert np.unique(np.asarray(a)).size == a.size  # no number handed out twice
    assert not np.array_equal(take(Draws(jax.random.PRNGKey(4))), a)
    d = Draws(key)
    assert draws(d) is d and isinstance(draws(key), Draws)


def test_uniform_bounds_and_moments():
    u = _many(lambda d: d.uniform((3,), jnp.array([0.0, -2.0, 5.0]), jnp.array([1.0, 2.0, 5.5])))
    lo, hi = np.array([0.0, -2.0, 5.0]), np.array([1.0, 2.0, 5.5])
    assert (u >= lo).all() and (u < hi).all()
    assert (np.abs(u.mean(0) - (lo + hi) / 2) < 4 * (hi - lo) / np.sqrt(12 * N)).all()
    np.testing.assert_allclose(u.var(0), (hi - lo) ** 2 / 12, rtol=0.05)
    # The columns of one key are independent.
    assert abs(np.corrcoef(u[:, 0], u[:, 1])[0, 1]) < 4 / np.sqrt(N)


def test_randint_covers_its_range_evenly_with_traced_bounds():
    def fn(d):
        hi = jnp.int32(3) + jnp.int32(4)  # traced: {2, ..., 6}
        return d.randint((), 2, hi)

    k = _many(fn)
    assert k.dtype == np.int32 and k.min() == 2 and k.max() == 6
    np.testing.assert_allclose(np.bincount(k)[2:] / N, 0.2, atol=4 * np.sqrt(0.16 / N))
    assert (_many(lambda d: d.randint((4,), 5, 5)) == 5).all()  # an empty range gives its start


def test_bernoulli_and_choice_frequencies():
    b = _many(lambda d: d.bernoulli(0.3, (2,)))
    np.testing.assert_allclose(b.mean(0), 0.3, atol=4 * np.sqrt(0.21 / N))
    p = jnp.array([1.0, 0.0, 3.0, 4.0])
    i = _many(lambda d: d.choice(p))
    np.testing.assert_allclose(np.bincount(i, minlength=4) / N, p / p.sum(), atol=0.012)
    assert (i != 1).all()  # a weight of 0 is never drawn


def test_normal_moments_and_tails():
    z = _many(lambda d: d.normal((2,))).ravel()
    assert np.isfinite(z).all()
    np.testing.assert_allclose([z.mean(), z.std()], [0.0, 1.0], atol=0.02)
    assert abs((np.abs(z) > 1.96).mean() - 0.05) < 0.006
    # The ends of the uniform's range map to finite values.
    ends = normal_of(jnp.array([0.0, 1.0 - 2.0**-24]))
    assert np.isfinite(np.asarray(ends)).all() and ends[0] < -5 and ends[1] > 5


@pytest.mark.parametrize("fold", [1, 2])
def test_blocks_are_apart_from_small_numbers_folded_into_the_key(fold):
    """Code that folds a small number into the episode key (e.g. the movers') draws numbers
    unrelated to the `Draws` of that key."""
    key = jax.random.PRNGKey(7)
    own = np.asarray(jax.random.uniform(jax.random.fold_in(key, fold), (BLOCK,)))
    d = Draws(key)
    blocks = np.concatenate([np.asarray(d.uniform((BLOCK,))) for _ in range(3)])
    assert not np.isin(own, blocks).any()


@pytest.mark.parametrize("keys", ["split", "sequential"])
def test_hashed_uniform_is_uniform_and_independent(keys):
    """The camera noise's hash (`hashed_uniform`): in [0, 1), even over 64 bins (chi-square),
    uncorrelated between neighbouring values of a key, between the two halves a step's noise and
    dropout read, and between neighbouring keys, even keys that differ in one counter (seeds
    0, 1, 2 ...); the same for a typed key as for its raw words."""
    n, shape = 4000, (2, 5, 24)
    if keys == "split":
        raw = jax.random.split(jax.random.PRNGKey(0), n)
    else:
        raw = jax.vmap(jax.random.PRNGKey)(jnp.arange(n))
    u = np.asarray(jax.jit(jax.vmap(lambda k: hashed_uniform(k, shape)))(raw)).reshape(n, -1)
    assert u.dtype == np.float32 and (u >= 0).all() and (u < 1).all()
    typed = jax.vmap(jax.random.wrap_key_data)(raw)
    np.testing.assert_array_equal(
        jax.vmap(lambda k: hashed_uniform(k, shape))(typed), u.reshape(n, *shape)
    )
    counts = np.bincount((u.ravel() * 64).astype(int), minlength=64)
    expected = u.size / 64
    assert ((counts - expected) ** 2 / expected).sum() < 120  # 63 degrees of freedom: mean 63
    np.testing.assert_allclose([u.mean(), u.var()], [0.5, 1 / 12], rtol=0.01)
    half = u.shape[1] // 2
    pairs = [
        (u[:, :-1].ravel(), u[:, 1:].ravel()),  # neighbouring values of a key
        (u[:, :half].ravel(), u[:, half:].ravel()),  # the noise's and the dropout's
        (u[:-1].ravel(), u[1:].ravel()),  # neighbouring keys
    ]
    for a, b in pairs:
        assert abs(np.corrcoef(a, b)[0, 1]) < 4 / np.sqrt(a.size)
    assert np.unique(u[:, 0]).size > 0.99 * n  # the first value of every key differs


@pytest.mark.parametrize("n", [1, 2, 5, 1000, 4096, 5000])
def test_hashed_permutation_is_a_permutation_of_its_key(n):
    """The learner's shuffle (`hashed_permutation`) takes every index below n once, whether n
    fills its cipher's domain (4,096: 2 x 6 bits) or not (the others keep the images below n);
    the same key gives the same order, another key another; a typed key as its raw words."""
    keys = jax.random.split(jax.random.PRNGKey(1), 3)
    perms = [np.asarray(jax.jit(hashed_permutation, static_argnums=1)(k, n)) for k in keys]
    for p in perms:
        assert p.dtype == np.int32 and np.array_equal(np.sort(p), np.arange(n))
    again = hashed_permutation(jax.random.wrap_key_data(keys[0]), n)
    np.testing.assert_array_equal(again, perms[0])
    if n >= 5:
        assert not np.array_equal(perms[0], perms[1]) and not np.array_equal(perms[1], perms[2])


@pytest.mark.parametrize("n", [16, 24])
def test_hashed_permutation_places_every_index_evenly(n):
    """Over 6,000 keys of the learner's kind (split from one another), each index lands in each
    position about equally often (chi-square over the n x n table), and a minibatch's members
    are independent of each other: two neighbouring indices fall in the same half of the order
    as often as a uniform shuffle puts them there ((n/2 - 1) / (n - 1))."""
    keys = jax.random.split(jax.random.PRNGKey(2), 6000)
    perms = np.asarray(jax.jit(jax.vmap(lambda k: hashed_permutation(k, n)))(keys))
    table = np.zeros((n, n))
    for position in range(n):
        table[:, position] = np.bincount(perms[:, position], minlength=n)
    expected = len(keys) / n
    chi2 = ((table - expected) ** 2 / expected).sum()
    dof = (n - 1) ** 2
    assert chi2 < dof + 5 * np.sqrt(2 * dof)
    where = np.argsort(perms, axis=1)  # [keys, n]: each index's position
    together = ((where[:, 0] < n // 2) == (where[:, 1] < n // 2)).mean()
    assert abs(together - (n / 2 - 1) / (n - 1)) < 0.03
