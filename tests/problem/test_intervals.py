"""The interval domain of the jaxpr walker: every enclosure holds the values the function computes at points of
the box (float64 and float32), points stay tight, and what has no rule is refused by name."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from firhc_jax._src.jaxpr.interpret import Unsupported
from firhc_jax._src.jaxpr.intervals import Interval, enclose

A = np.array([[0.5, -1.2, 2.0], [0.0, 3.0, -0.7]])
TABLE = np.array([0.3, -2.0, 1.5, 4.0, -0.1])

FUNCTIONS = {
    "arithmetic": lambda x: jnp.stack([x[0] + x[1] * x[2] - x[0] / (2 + x[1] ** 2), x[0] - x[0], x[1] * x[1]]),
    "transcendental": lambda x: jnp.stack([jnp.tanh(x[0]), jnp.exp(x[1]), jnp.log(1 + x[2] ** 2),
                                           jnp.sqrt(jnp.abs(x[0])), jax.nn.sigmoid(x[1]), jnp.log1p(x[2] ** 2)]),
    "trigonometric": lambda x: jnp.stack([jnp.sin(3 * x[0]), jnp.cos(x[1]), jnp.abs(jnp.sin(3 * x)).sum()]),
    "powers": lambda x: jnp.stack([x[0] ** 3, x[1] ** 4, 1 / (1 + x[2] ** 2), (1 + x[0] ** 2) ** 0.7,
                                   (2.5 + x[1]) ** -1, (3 + x[2]) ** -3, (0.5 + x[0] ** 2) ** -2]),
    "order": lambda x: jnp.stack([jnp.maximum(x[0], x[1]), jnp.minimum(x[1], x[2]), jnp.clip(x[2], -0.5, 0.5),
                                  jnp.where(x[0] > 0, x[0], -2 * x[0]), jnp.sort(x)[1], jnp.sign(x[2])]),
    "linear algebra": lambda x: jnp.concatenate([A @ x, jnp.cumsum(x), jnp.sum(x * x, keepdims=True)]),
    "indexing": lambda x: jnp.stack([jnp.asarray(TABLE)[jnp.clip(x[0].astype(int) + 2, 0, 4)],
                                     jnp.asarray(TABLE)[jnp.argmax(x)], x[jnp.array([2, 0])].sum()]),
    "loops": lambda x: jnp.stack([jax.lax.fori_loop(0, 3, lambda i, v: 0.9 * v + 0.1 * x[1], x[0]),
                                  jax.lax.cond(x[2] > 0, lambda v: v[0] * 2.0, lambda v: v[1] - 1.0, x)]),
    "logic": lambda x: jnp.stack([(x[0] < x[1]) & (x[2] > 0), ~(x[1] == 0.25) | (x[0] >= 1), x[0] != x[0],
                                  jnp.isfinite(x[1]), jnp.logical_xor(x[0] > 0, x[1] > 0)]),
    "remainder": lambda x: jnp.stack([jnp.fmod(x[0], 1.5), jnp.mod(x[1], 2.0)]),
}


def _check(fn, lo, hi, rng, samples=400):
    closed = jax.make_jaxpr(fn)(jnp.asarray(lo))
    low, high = jax.jit(lambda lo, hi: tuple(
        (e.lo, e.hi) for e in enclose(closed, [Interval(lo, hi)])))(jnp.asarray(lo), jnp.asarray(hi))[0]
    points = lo + (hi - lo) * rng.uniform(0, 1, (samples, lo.size)).astype(lo.dtype)
    corners = np.array(np.meshgrid(*zip(lo, hi, strict=True))).reshape(lo.size, -1).T.astype(lo.dtype)
    inputs = np.concatenate([points, corners, [lo, hi]])
    values = np.asarray(jax.jit(jax.vmap(fn))(jnp.asarray(inputs)))
    low, high = np.asarray(low), np.asarray(high)
    if lo.dtype == np.float32 and jax.config.jax_enable_x64 and values.dtype != bool:
        # the real values too (float64 stands in for them): what rounding outward is for
        values = np.concatenate([values, np.asarray(jax.jit(jax.vmap(fn))(jnp.asarray(inputs, jnp.float64)))])
    if values.dtype == bool:
        assert not np.any(values & ~high), "a value that can be True is said to be surely False"
        assert not np.any(~values & low), "a value that can be False is said to be surely True"
    else:
        ok = (values >= low) & (values <= high) | np.isnan(values)
        assert ok.all(), (low, high, values[~ok.all(axis=1)][:3])
    return low, high


@pytest.mark.float32
@pytest.mark.parametrize("dtype", [np.float64, np.float32])
@pytest.mark.parametrize("name", sorted(FUNCTIONS))
def test_enclosures_hold_every_value_in_the_box(name, dtype):
    if dtype == np.float64 and not jax.config.jax_enable_x64:
        pytest.skip("float64 needs x64")
    rng = np.random.default_rng(sorted(FUNCTIONS).index(name))
    for scale in (1e-6, 0.3, 3.0):
        center = rng.uniform(-2, 2, 3)
        lo = (center - scale * rng.uniform(0, 1, 3)).astype(dtype)
        hi = (center + scale * rng.uniform(0, 1, 3)).astype(dtype)
        _check(FUNCTIONS[name], lo, hi, rng)


def test_points_stay_within_a_few_ulps_and_linear_maps_are_exact():
    x = np.array([0.3, -1.1, 2.0])
    closed = jax.make_jaxpr(FUNCTIONS["transcendental"])(jnp.asarray(x))
    out = enclose(closed, [Interval(jnp.asarray(x))])[0]
    value = np.asarray(FUNCTIONS["transcendental"](jnp.asarray(x)))
    assert np.all(np.asarray(out.hi) - np.asarray(out.lo) <= 1e-12 * (1 + np.abs(value)))
    lo, hi = np.array([-1.0, 0.0, 0.5]), np.array([1.0, 0.5, 1.5])
    closed = jax.make_jaxpr(lambda v: A @ v)(jnp.asarray(lo))
    box = enclose(closed, [Interval(jnp.asarray(lo), jnp.asarray(hi))])[0]
    exact_lo = np.minimum(A * lo, A * hi).sum(axis=1)
    exact_hi = np.maximum(A * lo, A * hi).sum(axis=1)
    np.testing.assert_allclose(box.lo, exact_lo, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(box.hi, exact_hi, rtol=1e-12, atol=1e-12)


def test_a_possible_nan_is_everything():
    closed = jax.make_jaxpr(lambda v: jnp.sqrt(v) < 1.0)(jnp.zeros(()))
    out = enclose(closed, [Interval(jnp.asarray(-1.0), jnp.asarray(4.0))])[0]
    assert not bool(out.lo) and bool(out.hi)  # sqrt(-1) is NaN, and NaN < 1 is False: possibly False too


def test_a_while_loop_is_refused_by_name():
    def fn(v):
        return jax.lax.while_loop(lambda c: c < 10.0, lambda c: c * 2.0, v)

    closed = jax.make_jaxpr(fn)(jnp.ones(()))
    with pytest.raises(Unsupported, match="'while'"):
        enclose(closed, [Interval(jnp.asarray(1.0), jnp.asarray(2.0))])


def test_a_possible_nan_stays_possible_through_the_functions_that_keep_it():
    """sqrt of a possibly negative value may be NaN; abs, 0 *, max and tanh of NaN are NaN, and NaN >= 0 is
    False: each comparison below must stay possibly False."""
    for fn in (lambda v: jnp.abs(jnp.sqrt(v)) >= 0, lambda v: 0.0 * jnp.sqrt(v) == 0,
               lambda v: jnp.maximum(jnp.sqrt(v), 1.0) >= 1.0, lambda v: jnp.tanh(jnp.sqrt(v)) >= -1.0,
               lambda v: jnp.max(jnp.stack([jnp.sqrt(v), v])) >= -5.0):
        closed = jax.make_jaxpr(fn)(jnp.zeros(()))
        out = enclose(closed, [Interval(jnp.asarray(-1.0), jnp.asarray(4.0))])[0]
        assert not bool(out.lo) and bool(out.hi)
    ok = enclose(jax.make_jaxpr(lambda v: jnp.abs(jnp.sqrt(v)) >= 0)(jnp.zeros(())),
                 [Interval(jnp.asarray(1.0), jnp.asarray(4.0))])[0]
    assert bool(ok.lo)  # no NaN possible: surely True
