"""The sDFS stack (``firhc_jax._src.search.stack``) on its own: push, pop, top and paths."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from firhc_jax._src.search import stack as stacks

N, K, M, n = 4, 2, 3, 2  # rows 0..N, K parents of M inputs: L = 6 nodes a row


def fresh():
    return stacks.init(N + 1, K, M, N, jnp.array([1.0, 2.0]), jnp.float64)


def batch(keys, row=2):
    """A stack whose root is taken, with one batch of the given keys at ``row``
    (depth 2), expanded from two depth-1 parents (inputs 0 and 2)."""
    keys = jnp.asarray(keys, jnp.float64)
    x = jnp.stack([keys, jnp.arange(keys.shape[0], dtype=jnp.float64)], 1)  # x = [key, index in the batch]
    parents = jnp.array([[0, -1, -1, -1], [2, -1, -1, -1]], jnp.int32)
    root_taken, _ = stacks.pop(fresh(), jnp.int32(0), 1)
    return stacks.push(root_taken, jnp.int32(row), x, 10 + keys, keys, parents)


def test_init_holds_only_the_root():
    s = fresh()
    assert int(stacks.top(s, jnp.inf)) == 0 and not int(stacks.top(s, jnp.inf)) < 0
    s, p = stacks.pop(s, jnp.int32(0), 1)
    np.testing.assert_array_equal(p.x[0], [1.0, 2.0])
    assert float(p.cost[0]) == 0 and float(p.key[0]) == 0 and np.all(np.asarray(p.path) == -1)
    assert int(stacks.top(s, jnp.inf)) < 0 and int(stacks.top(s, jnp.inf)) == -1


def test_push_writes_only_its_row():
    before = batch([5, 3, 4, 1, 2, 6])
    after = stacks.push(before, jnp.int32(3), jnp.ones((K * M, n)), jnp.ones(K * M), jnp.full(K * M, 7.0),
                        jnp.zeros((K, N), jnp.int32))
    for field in stacks.Stack._fields:
        a, b = np.asarray(getattr(before, field)), np.asarray(getattr(after, field))
        np.testing.assert_array_equal(np.delete(a, 3, axis=0), np.delete(b, 3, axis=0), err_msg=field)
    assert float(after.low[3]) == 7.0 and int(stacks.top(after, jnp.inf)) == 3


def test_pop_takes_the_cheapest_first_and_ties_by_lowest_index():
    s = batch([3.0, 1.0, 2.0, 1.0, 5.0, 1.0])
    taken = []
    for _ in range(3):
        s, p = stacks.pop(s, jnp.int32(2), 2)
        taken += np.asarray(p.x).tolist()
        np.testing.assert_array_equal(p.cost, 10 + p.key)
    assert taken == [[1, 1], [1, 3], [1, 5], [2, 2], [3, 0], [5, 4]]  # [key, index] in pop order
    assert int(stacks.top(s, jnp.inf)) < 0


def test_pop_ties_in_index_order_gives_paths():
    s = batch([1.0, 1.0, 1.0, 1.0, 1.0, 1.0])
    s, p = stacks.pop(s, jnp.int32(2), 4)
    # node i of row 2: input i % M after parent i // M (inputs 0, then 2 at depth 0)
    np.testing.assert_array_equal(p.path, [[0, 0, -1, -1], [0, 1, -1, -1], [0, 2, -1, -1], [2, 0, -1, -1]])


def test_top_follows_the_bound_and_empty_rows():
    s = batch([4.0, 6.0, 5.0, 9.0, 7.0, 8.0])
    assert int(stacks.top(s, jnp.inf)) == 2
    assert int(stacks.top(s, 4.0)) == -1 and int(stacks.top(s, 4.0)) < 0  # nothing below 4: pruned as a whole
    assert int(stacks.top(s, 4.5)) == 2
    s, p = stacks.pop(s, jnp.int32(2), 1)
    assert float(p.key[0]) == 4.0 and float(s.low[2]) == 5.0  # the row's next key


def test_pop_outside_the_stack_takes_nothing():
    s = batch([4.0, 6.0, 5.0, 9.0, 7.0, 8.0])
    for row in (-1, N + 1):
        t, p = stacks.pop(s, jnp.int32(row), 2)
        assert np.all(np.isinf(np.asarray(p.key)))
        for field in stacks.Stack._fields:
            np.testing.assert_array_equal(np.asarray(getattr(s, field)), np.asarray(getattr(t, field)))


def test_child_path_sets_the_depth_entry():
    parents = jnp.array([[1, 0, -1, -1], [2, 2, -1, -1]], jnp.int32)  # two nodes of depth 2
    every_child = jnp.arange(K * M, dtype=jnp.int32)
    paths = np.asarray(jax.vmap(stacks.child_path, in_axes=(None, None, None, 0))(parents, jnp.int32(2), M,
                                                                                  every_child))
    assert paths.shape == (K * M, N)
    np.testing.assert_array_equal(paths[:, :2], [[1, 0]] * M + [[2, 2]] * M)
    np.testing.assert_array_equal(paths[:, 2], [0, 1, 2, 0, 1, 2])
    assert np.all(paths[:, 3] == -1)


@pytest.mark.parametrize("seed", range(3))
def test_vmapped_stacks_are_independent(seed):
    """Batched searches vmap the stack: each slot pops its own row."""
    rng = np.random.default_rng(seed)
    keys = rng.integers(0, 5, (3, K * M)).astype(float)
    many = jax.vmap(lambda k: batch(k))(jnp.asarray(keys))
    rows = jnp.array([2, -1, 2], jnp.int32)
    _, p = jax.vmap(stacks.pop, in_axes=(0, 0, None))(many, rows, 1)
    assert float(p.key[0, 0]) == keys[0].min() and np.isinf(float(p.key[1, 0])) and float(p.key[2, 0]) == keys[2].min()
