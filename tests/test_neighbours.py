"""b3dgs.neighbours (cKDTree) gives, bit for bit, the distances and picks of the brute-force loops it replaced:
the pool spacing and greedy picks of batch=diverse, acquisition=farthest and the OOD support scores."""
import numpy as np
import pytest

from b3dgs.acquisition import _pool_spacing, diverse_picks, greedy_spread
from b3dgs.neighbours import nearest_distances, nearest_other_distances
from b3dgs.report.ood import support_distances


def _brute_nearest(points, to):
    return np.linalg.norm(points[:, None] - to[None], axis=-1).min(axis=1) if len(to) else np.full(len(points), np.inf)


def _brute_spacing(points):
    if len(points) < 2:
        return 0.0
    d = np.linalg.norm(points[:, None] - points[None], axis=-1)
    np.fill_diagonal(d, np.inf)
    return float(np.median(d.min(axis=1)))


def _brute_diverse(scores, cand, train, budget, radius):
    s = np.asarray(scores, dtype=np.float64)
    if len(s) and s.min() < 0:
        s = s - s.min()
    h = _brute_spacing(np.concatenate([train.reshape(-1, 3), cand.reshape(-1, 3)]))
    scale2 = 2.0 * (float(radius) * h) ** 2
    d = _brute_nearest(cand, train)
    picks = []
    for _ in range(min(int(budget), len(cand))):
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            gain = np.where(np.isinf(d), 1.0, -np.expm1(-np.square(d) / scale2) if scale2 > 0 else (d > 0) * 1.0)
        value = s * gain
        value[picks] = -np.inf
        i = int(np.argmax(value))
        picks.append(i)
        d = np.minimum(d, np.linalg.norm(cand - cand[i], axis=-1))
    return picks, h


def _brute_farthest(cand, train, budget):
    d = _brute_nearest(cand, train)
    scores = d.tolist()
    picks = []
    for _ in range(min(int(budget), len(cand))):
        i = int(np.argmax(np.where(np.isin(np.arange(len(cand)), picks), -np.inf, d)))
        picks.append(i)
        d = np.minimum(d, np.linalg.norm(cand - cand[i], axis=-1))
    return picks, scores


def _cloud(rng, n, scale=3.0):
    # camera centres come from float32 poses, as double: the same kind of values as in the studies
    p = (rng.normal(size=(n, 3)) * scale).astype(np.float32).astype(np.float64)
    if n > 3:
        p[n // 2] = p[0]  # a duplicate
    return p


@pytest.mark.parametrize("seed", range(6))
def test_distances_equal_the_brute_force_bit_for_bit(seed):
    rng = np.random.default_rng(seed)
    pts, to = _cloud(rng, 300 + seed), _cloud(rng, 40 + 7 * seed, scale=2.0)
    assert np.array_equal(nearest_distances(pts, to), _brute_nearest(pts, to))
    assert _pool_spacing(pts) == _brute_spacing(pts)
    k3 = nearest_other_distances(pts, 3)
    d = np.linalg.norm(pts[:, None] - pts[None], axis=-1)
    np.fill_diagonal(d, np.inf)
    assert np.array_equal(k3, np.sort(d, axis=1)[:, :3])
    ref = np.array([np.linalg.norm(to - t, axis=1).min() / 2.5 for t in pts])
    assert np.array_equal(support_distances(to, pts, 2.5), ref)


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("radius", [0.0, 0.5, 2.0, 1e6])
def test_greedy_picks_equal_the_brute_force(seed, radius):
    rng = np.random.default_rng(100 + seed)
    cand, train = _cloud(rng, 60), _cloud(rng, 12 if seed else 0)
    scores = rng.normal(size=len(cand)).tolist()
    assert diverse_picks(scores, cand, train, 10, radius) == _brute_diverse(scores, cand, train, 10, radius)
    picks, d = greedy_spread(cand, train, 10, lambda d: d)
    assert (picks, d.tolist()) == _brute_farthest(cand, train, 10)


def test_empty_sets():
    assert nearest_distances(np.zeros((0, 3)), np.ones((2, 3))).shape == (0,)
    assert np.isinf(nearest_distances(np.ones((2, 3)), np.zeros((0, 3)))).all()
    assert _pool_spacing(np.ones((1, 3))) == 0.0
