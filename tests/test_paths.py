"""Quintic waypoint paths: continuity, derivatives against finite differences, rest at waypoints.

Central differences with step h = 1e-6 s: truncation h²·|x⁽³⁾|/6 ≲ 1e-10 and rounding
1e-16/1e-6 = 1e-10 for ẋ_d; for ẍ_d (FD of ẋ_d) the same orders. Tolerance 1e-7 (paths here
move ~1 m in ~1 s, so ẋ_d, ẍ_d are O(1–10)).
"""

from __future__ import annotations

import numpy as np
import pytest

from qpctl import ConfigError, WaypointPath
from qpctl.paths import quintic

H = 1e-6


@pytest.fixture
def path() -> WaypointPath:
    pts = [[-1.0, -2.0], [0.2, -1.5], [1.0, -1.5], [0.5, -0.4]]
    return WaypointPath(pts, durations=[1.0, 0.7, 1.3], start_time=0.25, dwell=0.2)


def test_quintic_profile():
    """s(τ) = 10τ³ − 15τ⁴ + 6τ⁵ and its derivatives, written independently (np.polyval)."""
    poly = np.array([6.0, -15.0, 10.0, 0.0, 0.0, 0.0])
    for tau in np.linspace(0.0, 1.0, 11):
        s, ds, dds = quintic(tau)
        assert s == pytest.approx(np.polyval(poly, tau), abs=1e-14)
        assert ds == pytest.approx(np.polyval(np.polyder(poly), tau), abs=1e-12)
        assert dds == pytest.approx(np.polyval(np.polyder(poly, 2), tau), abs=1e-12)
    assert quintic(-0.5) == (0.0, 0.0, 0.0) and quintic(1.5) == (1.0, 0.0, 0.0)


def test_derivatives_equal_finite_differences(path, rng):
    times = np.concatenate([rng.uniform(0.0, path.end_time + 0.5, 40), [0.3, 1.0, 2.2]])
    for t in times:
        r = path(t)
        fd_v = (path(t + H).x - path(t - H).x) / (2 * H)
        fd_a = (path(t + H).xd - path(t - H).xd) / (2 * H)
        np.testing.assert_allclose(r.xd, fd_v, atol=1e-7)
        np.testing.assert_allclose(r.xdd, fd_a, atol=1e-6)


def test_continuity_and_rest_at_waypoints(path):
    """x_d, ẋ_d, ẍ_d continuous everywhere (also across segment joints and dwells); ẋ_d = ẍ_d = 0 at waypoints."""
    t = np.linspace(-0.2, path.end_time + 0.2, 20001)
    refs = [path(tk) for tk in t]
    x = np.array([r.x for r in refs])
    xd = np.array([r.xd for r in refs])
    dt = t[1] - t[0]
    vmax = np.abs(xd).max()
    # Lipschitz continuity of x_d on a fine grid: no jump bigger than v_max dt (plus rounding).
    assert np.abs(np.diff(x, axis=0)).max() <= vmax * dt * 1.001 + 1e-12
    # Waypoint times: every segment start and end.
    ends = path.starts + path.durations
    for k, (t0, t1) in enumerate(zip(path.starts, ends)):
        for tk, pk in ((t0, path.points[k]), (t1, path.points[k + 1])):
            for tt in (tk - 1e-9, tk, tk + 1e-9):
                r = path(tt)
                np.testing.assert_allclose(r.x, pk, atol=1e-8)
                np.testing.assert_allclose(r.xd, 0.0, atol=1e-6)
                np.testing.assert_allclose(r.xdd, 0.0, atol=1e-6)
    # Before the start and after the end the reference holds still.
    for tt, p in ((-1.0, path.points[0]), (0.0, path.points[0]), (path.end_time + 3.0, path.points[-1])):
        r = path(tt)
        np.testing.assert_allclose(r.x, p)
        assert not np.any(r.xd) and not np.any(r.xdd)
    # During a dwell the path waits at the waypoint.
    np.testing.assert_allclose(path(ends[0] + 0.1).x, path.points[1])


def test_straight_segments_between_waypoints(path, rng):
    """Every x_d lies on its segment; ẋ_d and ẍ_d are parallel to it."""
    for k in range(len(path.durations)):
        a, b = path.points[k], path.points[k + 1]
        u = (b - a) / np.linalg.norm(b - a)
        for t in rng.uniform(path.starts[k], path.starts[k] + path.durations[k], 5):
            r = path(t)
            w = r.x - a
            assert abs(w[0] * u[1] - w[1] * u[0]) < 1e-12
            assert abs(r.xd[0] * u[1] - r.xd[1] * u[0]) < 1e-12
            assert abs(r.xdd[0] * u[1] - r.xdd[1] * u[0]) < 1e-12


def test_total_duration_is_shared_by_length():
    p = WaypointPath([[0.0, 0.0], [3.0, 0.0], [3.0, 1.0]], duration=4.0)
    np.testing.assert_allclose(p.durations, [3.0, 1.0])
    assert p.end_time == pytest.approx(4.0)
    # The peak speed of a quintic over distance D in time T is 15 D / (8 T).
    speeds = [np.linalg.norm(p(t).xd) for t in np.linspace(0, 3, 3001)]
    assert max(speeds) == pytest.approx(15 * 3 / (8 * 3), rel=1e-6)


def test_constant_reference():
    """A path whose waypoint equals its start is a constant reference (used for regulation)."""
    p = WaypointPath([[0.5, -1.0], [0.5, -1.0]], duration=1.0)
    for t in (0.0, 0.3, 5.0):
        r = p(t)
        np.testing.assert_allclose(r.x, [0.5, -1.0])
        assert not np.any(r.xd) and not np.any(r.xdd)


@pytest.mark.parametrize("kwargs, key", [
    ({"points": [[0.0, 0.0]], "duration": 1.0}, "path.waypoints"),
    ({"points": [[0.0, 0.0], [np.nan, 1.0]], "duration": 1.0}, "path.waypoints"),
    ({"points": [[0.0, 0.0], [1.0, 1.0]]}, "path.duration"),
    ({"points": [[0.0, 0.0], [1.0, 1.0]], "duration": -2.0}, "path.duration"),
    ({"points": [[0.0, 0.0], [0.0, 0.0]], "duration": -2.0}, "path.duration"),
    ({"points": [[0.0, 0.0], [1.0, 1.0]], "durations": [0.0]}, "path.duration"),
    ({"points": [[0.0, 0.0], [1.0, 1.0]], "durations": [1.0, 2.0]}, "path.durations"),
    ({"points": [[0.0, 0.0], [1.0, 1.0]], "duration": 1.0, "dwell": -1.0}, "path.dwell"),
])
def test_bad_paths_name_the_key(kwargs, key):
    points = kwargs.pop("points")
    with pytest.raises(ConfigError) as exc:
        WaypointPath(points, **kwargs)
    assert exc.value.key == key
