"""The two-sided refinement's map-to-plan term (:func:`frslam_graph.registration.refine._wall_terms`),
computed in the plan's scaled axes, against the same residual written in the map frame."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial import cKDTree

from frslam_graph.registration.refine import WALL_NEIGHBOURS, _wall_terms


def _map_frame_residuals(x: np.ndarray, f: float, p, n, walls, jj, off: float, xn=None) -> np.ndarray:
    """Signed distance (metres) of each wall cell from the line of the best of its candidate plan
    samples ``jj``, minus ``off``: samples placed by R(theta) diag(1, f) diag(sx, sy) p + t, the
    lines' normals by the inverse transpose (at the parameters ``xn``, default ``x``), all in the
    map frame."""
    xn = x if xn is None else xn
    c, s = math.cos(x[0]), math.sin(x[0])
    rot = np.array([[c, -s], [s, c]])
    a = rot @ np.diag([1.0, f]) @ np.diag([math.exp(x[3]), math.exp(x[4])])
    q = p @ a.T + x[1:3]
    cn, sn = math.cos(xn[0]), math.sin(xn[0])
    rn = np.array([[cn, -sn], [sn, cn]])
    m = n @ (rn @ np.diag([1.0, f]) @ np.diag([math.exp(-xn[3]), math.exp(-xn[4])])).T
    m /= np.hypot(m[:, 0], m[:, 1])[:, None]
    sd = ((walls[:, None, :] - q[jj]) * m[jj]).sum(axis=2) - off
    return sd[np.arange(len(walls)), np.argmin(np.abs(sd), axis=1)]


@pytest.mark.parametrize("flipped", [False, True])
def test_wall_term_matches_the_map_frame_residual_and_its_derivatives(flipped):
    rng = np.random.default_rng(3)
    f = -1.0 if flipped else 1.0
    # plan samples on a few axis-aligned and slanted walls, unit normals
    t = rng.uniform(0.0, 8.0, 120)
    p = np.column_stack([t, np.repeat([0.0, 3.0, 5.0], 40)])
    n = np.tile([0.0, 1.0], (120, 1)) * np.repeat([1.0, -1.0, 1.0], 40)[:, None]
    p[80:] = np.column_stack([2.0 + t[80:] * 0.6, 1.0 + t[80:] * 0.8])
    n[80:] = [-0.8, 0.6]
    x = np.array([0.7, 1.3, -2.1, math.log(1.04), math.log(0.97), 0.06])
    delta, res = x[5], 0.05
    off = delta + 0.5 * res
    # the map's wall cells: samples placed, pushed off their lines by a few centimetres
    c, s = math.cos(x[0]), math.sin(x[0])
    rot = np.array([[c, -s], [s, c]])
    a = rot @ np.diag([1.0, f]) @ np.diag([math.exp(x[3]), math.exp(x[4])])
    walls = (p[::3] + rng.normal(0.0, 0.04, (40, 2))) @ a.T + x[1:3]
    jj = cKDTree(p).query((walls - x[1:3]) @ np.linalg.inv(a).T, k=WALL_NEIGHBOURS)[1]
    dx, dy = walls[:, 0] - x[1], walls[:, 1] - x[2]
    vx, vy = c * dx + s * dy, c * dy - s * dx
    ax, ay = math.exp(x[3]) * p[:, 0], f * math.exp(x[4]) * p[:, 1]
    jm, rm, wm = _wall_terms(
        vx, vy, jj, n[:, 0], f * n[:, 1], ax, ay, math.exp(-x[3]), math.exp(-x[4]), c, s, off, 0.1
    )
    np.testing.assert_allclose(rm, _map_frame_residuals(x, f, p, n, walls, jj, off), atol=1e-12)
    np.testing.assert_allclose(wm, 1.0 / (1.0 + (rm / 0.1) ** 2), rtol=1e-12)
    # the Jacobian in (theta, tx, ty, log sx, log sy) against central differences, the lines'
    # normals held (Gauss-Newton on point-to-line distances, as ICP), each cell on its nearest
    # sample's line (of several samples on one line, the pick is a tie)
    j1 = jj[:, :1]
    jm, _, _ = _wall_terms(
        vx, vy, j1, n[:, 0], f * n[:, 1], ax, ay, math.exp(-x[3]), math.exp(-x[4]), c, s, off, 0.1
    )
    for k in range(5):
        h = np.zeros(6)
        h[k] = 1e-6
        num = (
            _map_frame_residuals(x + h, f, p, n, walls, j1, off, x)
            - _map_frame_residuals(x - h, f, p, n, walls, j1, off, x)
        ) / 2e-6
        np.testing.assert_allclose(jm[:, k], num, atol=1e-6)
