"""The distance field's kernels: the EDT against scipy's, the trilinear lookup against scipy's
map_coordinates and finite differences, and the link–field pairs against a dense search and the
analytic capsule–point distance (qpctl.kernels.edt, qpctl.kernels.field; issue 21, items 1 and 4)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from qpctl.kernels import edt as KE
from qpctl.kernels import field as KF
from qpctl.perception import reference as ref
from qpctl.perception.snapshot import VoxelGrid

GRID = VoxelGrid(np.array([-0.3, -0.2, 0.1]), 0.02, (30, 24, 20))
TRUNC = 0.2


def _field(occ: np.ndarray, voxel: float = GRID.voxel, trunc: float = TRUNC) -> tuple[np.ndarray, np.ndarray]:
    dist = np.empty(occ.shape, np.float32)
    grad = np.empty(occ.shape + (3,), np.float32)
    KE.distance_field(occ, voxel, trunc, np.empty((2, *occ.shape), np.float32), dist)
    KE.gradient(dist, voxel, grad)
    return dist, grad


@pytest.mark.parametrize("shape,density", [((30, 24, 20), 0.002), ((30, 24, 20), 0.05), ((1, 17, 9), 0.1),
                                           ((40, 1, 1), 0.05), ((8, 8, 8), 1.0), ((12, 10, 9), 0.0)])
def test_edt_matches_scipy(shape: tuple[int, int, int], density: float, rng: np.random.Generator) -> None:
    occ = rng.uniform(size=shape) < density
    for trunc in (0.05, 0.06, 0.2, 10.0):  # 0.05: a cap of 6.25 voxels², not a square
        dist = np.empty(shape, np.float32)
        n = KE.distance_field(occ, 0.02, trunc, np.empty((2, *shape), np.float32), dist)
        assert n == occ.sum()
        assert dist == pytest.approx(ref.distance_field(occ, 0.02, trunc), abs=1e-6)


def test_edt_of_one_voxel_is_the_euclidean_distance() -> None:
    occ = np.zeros(GRID.shape, bool)
    occ[10, 7, 4] = True
    dist, _ = _field(occ, trunc=10.0)
    idx = np.indices(GRID.shape).reshape(3, -1).T
    exact = np.linalg.norm((idx - [10, 7, 4]) * GRID.voxel, axis=1).reshape(GRID.shape)
    assert dist == pytest.approx(exact, abs=1e-6)


def test_gradient_grid_is_numpys_gradient(rng: np.random.Generator) -> None:
    occ = rng.uniform(size=GRID.shape) < 0.01
    dist, grad = _field(occ)
    expect = np.stack(np.gradient(dist.astype(float), GRID.voxel), axis=-1)
    assert grad == pytest.approx(expect, abs=1e-4)


def test_trilinear_matches_scipys_map_coordinates(rng: np.random.Generator) -> None:
    occ = rng.uniform(size=GRID.shape) < 0.01
    dist, grad = _field(occ)
    pts = rng.uniform(GRID.origin - 0.05, GRID.upper + 0.05, (2000, 3))
    d_ref, g_ref = ref.field_at(dist, grad, GRID, TRUNC, pts)
    g = np.empty(3)
    for p, dr, gr in zip(pts, d_ref, g_ref, strict=True):
        d = KF.trilinear(dist, grad, GRID.origin, GRID.voxel, TRUNC, p[0], p[1], p[2], True, g)
        assert d == pytest.approx(dr, abs=1e-5)
        assert g == pytest.approx(gr, abs=1e-4)


def test_trilinear_gradient_is_the_derivative_of_the_distance(rng: np.random.Generator) -> None:
    occ = rng.uniform(size=GRID.shape) < 0.01
    dist, grad = _field(occ)
    g, gp, gm = np.empty(3), np.empty(3), np.empty(3)
    h = 1e-6
    for p in rng.uniform(GRID.origin + 0.02, GRID.upper - 0.02, (300, 3)):
        KF.trilinear(dist, grad, GRID.origin, GRID.voxel, TRUNC, p[0], p[1], p[2], False, g)
        fd = [(KF.trilinear(dist, grad, GRID.origin, GRID.voxel, TRUNC, *(p + h * e), False, gp)
               - KF.trilinear(dist, grad, GRID.origin, GRID.voxel, TRUNC, *(p - h * e), False, gm)) / (2 * h)
              for e in np.eye(3)]
        assert g == pytest.approx(fd, abs=1e-4 + 1e-3 * np.abs(fd).max())


def _segments(rng: np.random.Generator, k: int) -> tuple[np.ndarray, np.ndarray]:
    a = rng.uniform(GRID.origin + 0.05, GRID.upper - 0.05, (k, 3))
    u = rng.normal(size=(k, 3))
    u *= rng.uniform(0.05, 0.2, (k, 1)) / np.linalg.norm(u, axis=1, keepdims=True)
    return np.stack([a, np.clip(a + u, GRID.origin, GRID.upper)], axis=1), rng.uniform(0.02, 0.05, k)


def _pairs(segs: np.ndarray, radii: np.ndarray, dist: np.ndarray, grad: np.ndarray, samples: int = 16,
           rows: int = 2, smooth: bool = True) -> tuple[np.ndarray, ...]:
    L = len(segs)
    out = (np.empty(L * rows), np.empty((L * rows, 3)), np.empty((L * rows, 3)), np.empty(L * rows))
    KF.field_pairs(segs, radii, dist, grad, GRID.origin, GRID.voxel, TRUNC, samples, rows, smooth,
                   np.empty(samples), *out)
    return out


def test_nearest_field_pair_matches_a_dense_search(rng: np.random.Generator) -> None:
    occ = np.zeros(GRID.shape, bool)
    for c in rng.integers(0, GRID.shape, (6, 3)):
        occ[c[0], c[1], c[2]] = True
    dist, grad = _field(occ)
    segs, radii = _segments(rng, 40)
    d, n, p, s = _pairs(segs, radii, dist, grad)
    d_ref, n_ref, p_ref = ref.field_pairs(segs, radii, dist, grad, GRID, TRUNC)
    active = d_ref < TRUNC - radii - 1e-6
    assert active.sum() > 20
    first = d[::2]
    # 16 samples and a parabola find the least distance along the axis to within a few mm
    assert np.all(first[active] >= d_ref[active] - 1e-6)
    assert first[active] == pytest.approx(d_ref[active], abs=0.004)
    # normals are unit, and (where the minimum is the same point) the dense search's
    assert np.allclose(np.linalg.norm(n[::2][active], axis=1), 1.0)
    close = active & (np.linalg.norm(p[::2] - p_ref, axis=1) < 0.005)
    assert close.sum() > 10 and np.all(np.einsum("ij,ij->i", n[::2][close], n_ref[close]) > 0.95)
    # the witness point lies on the capsule's surface: axis point − r n
    axis = segs[:, 0] + s[::2, None] * (segs[:, 1] - segs[:, 0])
    assert np.allclose(p[::2][active], axis[active] - radii[active, None] * n[::2][active])
    # inactive rows: distance = truncation − r, zero normal
    assert np.allclose(d[::2][~active], TRUNC - radii[~active]) and not n[::2][~active].any()


def test_field_pair_to_a_point_obstacle_is_the_capsule_point_distance() -> None:
    """One occupied voxel: the field is the exact distance to its centre, so a link's row is the
    capsule–point distance and its normal the direction from the point to the axis (within the
    trilinear interpolation's error)."""
    occ = np.zeros(GRID.shape, bool)
    occ[15, 12, 10] = True
    c = GRID.centres(np.array([[15, 12, 10]]))[0]
    dist, grad = _field(occ)
    segs = np.array([[c + [-0.1, 0.08, 0.03], c + [0.1, 0.08, 0.03]], [c + [0.05, -0.12, -0.1], c + [0.05, 0.0, 0.1]]])
    radii = np.array([0.03, 0.04])
    d, n, _, s = _pairs(segs, radii, dist, grad, rows=1)
    for i, ((a, b), r) in enumerate(zip(segs, radii, strict=True)):
        t = np.clip((c - a) @ (b - a) / ((b - a) @ (b - a)), 0, 1)
        q = a + t * (b - a)
        assert d[i] == pytest.approx(np.linalg.norm(q - c) - r, abs=0.003)
        assert n[i] @ (q - c) / np.linalg.norm(q - c) > 0.99
        assert s[i] == pytest.approx(t, abs=0.05)


def test_second_row_is_a_separate_local_minimum() -> None:
    occ = np.zeros(GRID.shape, bool)
    occ[5, 12, 10] = occ[25, 12, 10] = True  # two points 0.4 m apart
    c0, c1 = GRID.centres(np.array([[5, 12, 10], [25, 12, 10]]))
    dist, grad = _field(occ, trunc=0.3)
    seg = np.array([[c0 + [-0.02, 0.08, 0], c1 + [0.02, 0.1, 0]]])
    L = 1
    out = (np.empty(2 * L), np.empty((2 * L, 3)), np.empty((2 * L, 3)), np.empty(2 * L))
    KF.field_pairs(seg, np.array([0.02]), dist, grad, GRID.origin, GRID.voxel, 0.3, 16, 2, True, np.empty(16), *out)
    d, _, _, s = out
    assert s[0] < 0.3 and s[1] > 0.7  # the nearer point at the left end, the other at the right
    assert d[0] == pytest.approx(math.hypot(0.02, 0.08) - 0.02, abs=0.004)
    assert d[1] == pytest.approx(math.hypot(0.02, 0.1) - 0.02, abs=0.004)


def test_smooth_rows_do_not_jump_as_the_nearest_voxel_changes() -> None:
    """A 0.3 m link sliding along its axis 6 cm above a point obstacle in 0.5 mm steps: its nearest
    point runs along the link. The smooth rows' witness point moves by about the step; the raw rows'
    jumps by up to a sample spacing (2 cm) and their normal turns by up to the angle the spacing subtends."""
    occ = np.zeros(GRID.shape, bool)
    occ[15, 12, 10] = True
    c = GRID.centres(np.array([[15, 12, 10]]))[0]
    dist, grad = _field(occ)

    def steps(smooth: bool) -> tuple[float, float, float]:
        prev = None
        dn = dp = dd = 0.0
        for x in np.arange(-0.1, 0.1, 0.0005):
            seg = np.array([[c + [x - 0.15, 0.0, 0.06], c + [x + 0.15, 0.0, 0.06]]])
            d, n, p, _ = _pairs(seg, np.array([0.02]), dist, grad, rows=1, smooth=smooth)
            if prev is not None:
                dn = max(dn, float(np.linalg.norm(n[0] - prev[1][0])))
                dp = max(dp, float(np.linalg.norm(p[0] - prev[2][0])))
                dd = max(dd, abs(float(d[0] - prev[0][0])))
            prev = (d, n, p)
        return dn, dp, dd

    smooth, raw = steps(True), steps(False)
    assert smooth[1] < 0.004 and smooth[0] < 0.1
    assert raw[1] > 0.01 and raw[0] > 3 * smooth[0]
    assert smooth[2] < 0.002  # the distance is continuous


def test_a_link_inside_a_solid_block_reports_its_depth_not_the_truncation() -> None:
    """Deep inside occupied voxels the field is flat (zero, no gradient): the row has no normal (no
    barrier) but its distance is still what the map believes, about −r (the capsule's axis on occupied
    voxels: cKDTree's distance from the axis samples to the occupied centres is 0), not the inactive
    row's truncation − r (a link buried in a branch reported as far away)."""
    from scipy.spatial import cKDTree

    occ = np.zeros(GRID.shape, bool)
    occ[8:22, 6:18, 5:15] = True  # a block 0.28 × 0.24 × 0.20 m
    dist, grad = _field(occ)
    centres = GRID.centres(np.argwhere(occ))
    mid = centres.mean(axis=0)
    segs = np.array([[mid - [0.04, 0.0, 0.0], mid + [0.04, 0.0, 0.0]]])
    radii = np.array([0.03])
    axis = segs[0, 0] + np.linspace(0, 1, 16)[:, None] * (segs[0, 1] - segs[0, 0])
    assert cKDTree(centres).query(axis)[0].max() < GRID.voxel  # the whole axis on occupied voxels
    d, n, _, _ = _pairs(segs, radii, dist, grad, rows=1)
    assert not n.any()  # flat: no normal, so no barrier row
    assert d[0] == pytest.approx(-radii[0], abs=GRID.voxel)


def _separate(segs: np.ndarray, radii: np.ndarray, dist: np.ndarray, grad: np.ndarray, trunc: float, samples: int,
              rows: int, smooth: bool, vel: np.ndarray, speed: tuple[float, float, float, float]
              ) -> tuple[np.ndarray, ...]:
    """Both channels' field_pairs and channel 1's speed_points, as the Python path calls them."""
    L = len(segs)
    d, n, p, s = np.empty(2 * L * rows), np.empty((2 * L * rows, 3)), np.empty((2 * L * rows, 3)), np.empty(2 * L * rows)
    for ch in range(2):
        b = slice(ch * L * rows, (ch + 1) * L * rows)
        KF.field_pairs(segs, radii, dist[ch], grad[ch], GRID.origin, GRID.voxel, trunc, samples, rows, smooth,
                       np.empty(samples), d[b], n[b], p[b], s[b])
    vp, vu, vb, vd = np.empty((2 * L, 3)), np.empty((2 * L, 3)), np.empty(2 * L), np.empty(2 * L)
    KF.speed_points(segs, radii, dist[1], GRID.origin, GRID.voxel, trunc, samples, vel, *speed, np.empty(samples),
                    vp, vu, vb, vd)
    return d, n, p, s, vp, vu, vb, vd


@pytest.mark.parametrize("samples,rows,smooth,trunc", [(12, 2, True, TRUNC), (16, 1, True, TRUNC),
                                                       (7, 2, False, TRUNC), (12, 2, True, 0.06), (2, 2, True, TRUNC)])
def test_one_pass_field_samples_equal_the_separate_kernels(samples: int, rows: int, smooth: bool, trunc: float,
                                                           rng: np.random.Generator) -> None:
    """qpctl.kernels.field_samples against field_pairs (both channels) and speed_points (the soft one):
    the same pairs (distance, normal, witness point, axis parameter) and speed points (point, direction,
    bound, distance), bit for bit, on random fields (the channels different) and capsules, some partly
    outside the grid; at trunc = 0.06 the fields (capped at 0.2) exceed the truncation passed, so the
    per-link early-out fires too."""
    from qpctl.kernels.field_samples import field_samples
    from qpctl.perception.snapshot import side_by_side

    for density in (0.003, 0.02, 0.0):
        dist = np.empty((2, *GRID.shape), np.float32)
        grad = np.empty((2, *GRID.shape, 3), np.float32)
        for ch in range(2):
            dist[ch], grad[ch] = _field(rng.uniform(size=GRID.shape) < density * (1 + ch))
        segs, radii = _segments(rng, 40)
        segs[:5] += rng.uniform(-0.3, 0.3, (5, 1, 3))  # some ends beyond the grid
        vel = rng.normal(0.0, 0.5, (len(segs), 6))
        vel[:3] = 0.0  # at rest: points without a direction
        speed = (0.05, 2.0, 0.01, 0.1 if density else 0.5)
        want = _separate(segs, radii, dist, grad, trunc, samples, rows, smooth, vel, speed)
        L = len(segs)
        got = (np.full(2 * L * rows, np.nan), np.full((2 * L * rows, 3), np.nan), np.full((2 * L * rows, 3), np.nan),
               np.full(2 * L * rows, np.nan), np.full((2 * L, 3), np.nan), np.full((2 * L, 3), np.nan),
               np.full(2 * L, np.nan), np.full(2 * L, np.nan))
        field_samples(segs, radii, dist, side_by_side(dist), grad, GRID.origin, GRID.voxel, trunc, samples, rows, smooth,
                      vel, *speed, np.empty((2, samples)), *got)
        for w, g in zip(want, got, strict=True):
            np.testing.assert_array_equal(g, w)
        if density:  # the comparison covers active pairs and speed rows
            assert np.sum(want[0] < trunc - np.tile(np.repeat(radii, rows), 2)) > 5
            assert np.isfinite(want[6]).sum() > 3
