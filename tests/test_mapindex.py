"""MapIndex's single nearest neighbours: queries inside the map's box from small_gicp's tree,
outside from SciPy's; the same answer as a brute-force search either way."""

from __future__ import annotations

import pickle

import numpy as np
import pytest

from icpbench.core.mapindex import MapIndex


def _map_and_queries(seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A street-like map (M, 3) and queries (K, 3): on it, beside it and tens of metres away,
    with a NaN row."""
    rng = np.random.default_rng(seed)
    ground = np.c_[rng.uniform(-20, 20, (3000, 2)), rng.normal(0, 0.02, 3000)]
    wall = np.c_[rng.uniform(-20, 20, 1500), np.full(1500, 6.0), rng.uniform(0, 4, 1500)]
    m = np.vstack([ground, wall])
    near = m[rng.integers(0, len(m), 800)] + rng.normal(0, 0.3, (800, 3))
    far = rng.uniform(-80, 80, (800, 3))
    q = np.vstack([near, far, [[np.nan, 0.0, 0.0]]])
    return m, q


def _brute(m: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    d = np.linalg.norm(q[:, None] - m[None], axis=-1)
    return d.min(axis=1), d.argmin(axis=1)


def test_query_is_the_brute_force_nearest_neighbour_near_the_map_and_far_from_it():
    m, q = _map_and_queries()
    index = MapIndex(m)
    ok = np.isfinite(q).all(axis=1)
    inside = index.near_map(q[ok])
    assert 0.3 < inside.mean() < 0.9  # both trees answer some of them
    d, i = index.query(q)
    d_ref, i_ref = _brute(m, q[ok])
    np.testing.assert_allclose(d[ok], d_ref, rtol=1e-12)
    assert np.array_equal(i[ok], i_ref)
    assert np.isinf(d[~ok]).all() and (i[~ok] == len(m)).all()


def test_query_distances_equal_small_gicps_to_the_bit_from_either_tree():
    # the plans' climbs are formed from these distances: the split must not change a bit
    m, q = _map_and_queries(1)
    q = q[np.isfinite(q).all(axis=1)]
    index = MapIndex(m)
    rows, d2 = index.tree.batch_knn_search(np.ascontiguousarray(q), 1, num_threads=1)
    d, i = index.query(q)
    assert np.array_equal(d, np.sqrt(np.asarray(d2)[:, 0]))
    assert np.array_equal(i, np.asarray(rows).astype(np.int64)[:, 0])


@pytest.mark.parametrize("max_dist", [0.5, 3.0, 30.0])
def test_a_bounded_query_is_the_unbounded_one_cut_at_the_bound(max_dist):
    m, q = _map_and_queries(2)
    index = MapIndex(m)
    d, i = index.query(q)
    d_b, i_b = index.query(q, max_dist)
    cut = ~(d < max_dist)
    assert np.array_equal(d_b, np.where(cut, np.inf, d))
    assert np.array_equal(i_b, np.where(cut, len(m), i))
    assert cut.any() and not cut.all()


def test_a_pickled_index_rebuilds_its_trees_and_answers_the_same():
    m, q = _map_and_queries(3)
    index = MapIndex(m)
    before = index.query(q)
    copy = pickle.loads(pickle.dumps(index))
    assert copy._tree is None and copy._far is None
    after = copy.query(q)
    assert np.array_equal(before[0], after[0]) and np.array_equal(before[1], after[1])


def test_a_map_with_a_duplicated_point_answers_every_query_from_small_gicps_tree():
    # two copies of a point: the trees may name different copies (with other normals), so the
    # whole map stays on small_gicp's tree, whose choice every earlier result was made with
    m, q = _map_and_queries(4)
    m = np.vstack([m, m[:1]])
    index = MapIndex(m)
    finite = q[np.isfinite(q).all(axis=1)]
    assert index.near_map(finite).all()
    rows, d2 = index.tree.batch_knn_search(np.ascontiguousarray(finite), 1, num_threads=1)
    d, i = index.query(finite)
    assert np.array_equal(i, np.asarray(rows).astype(np.int64)[:, 0])
    assert np.array_equal(d, np.sqrt(np.asarray(d2)[:, 0]))
    assert not MapIndex(m[:-1]).near_map(finite).all()
