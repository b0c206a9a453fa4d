"""Small helpers shared by the MFR steps: rotations, the dihedral group, wall directions, and
raster lookups at metric points.

Angles are radians; a raster has row 0 at the lowest y, cells of ``resolution`` metres (or plan
units) from ``origin``.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

DIHEDRAL: tuple[tuple[int, bool], ...] = tuple((k, f) for f in (False, True) for k in range(4))


def dihedral(k: int, flipped: bool) -> np.ndarray:
    """2×2 ``R(k·90°) · diag(1, -1 if flipped)`` with exact integer entries."""
    c, s = [(1, 0), (0, 1), (-1, 0), (0, -1)][k % 4]
    r = np.array([[c, -s], [s, c]], dtype=np.float64)
    return r @ np.diag([1.0, -1.0 if flipped else 1.0])


#: vectors :func:`dominant_angles` takes at most (a regular subsample of more keeps the histogram)
ANGLE_SAMPLES = 6000


def regular_subsample(a: np.ndarray, cap: int) -> np.ndarray:
    """Every k-th element of ``a`` (k = ceil(len / cap)) when it holds more than ``cap``; else ``a``."""
    return a[:: int(math.ceil(len(a) / cap))] if len(a) > cap else a


def dominant_angles(vectors: np.ndarray, max_peaks: int = 2, rel: float = 0.35) -> list[float]:
    """Wall directions modulo 90° (radians in (-pi/4, pi/4]) of (N, 2) vectors weighted by their
    length: peaks of a circular histogram (smoothed, σ = 3°), the strongest first, each refined by
    the weighted circular mean within ±10°; a second peak counts when it is at least ``rel`` of
    the first and 20° away. Robust to a few diagonal walls, unlike one overall mean."""
    vectors = regular_subsample(vectors, ANGLE_SAMPLES)
    mag = np.hypot(vectors[:, 0], vectors[:, 1])
    ok = mag > 0
    if ok.all():  # the map's gradients: every one (the same arrays as indexed by ``ok``)
        v, w = vectors, mag
    elif not ok.any():
        return [0.0]
    else:
        v, w = vectors[ok], mag[ok]
    a4 = np.mod(4.0 * np.arctan2(v[:, 1], v[:, 0]), 2 * np.pi)  # 4x angle: walls at 90° agree
    bins = 360
    hist = np.bincount((a4 / (2 * np.pi) * bins).astype(np.intp) % bins, weights=w, minlength=bins)
    # smoothing σ = 3° of wall angle (12 bins of the 4x angle): gradients of rasterised oblique
    # walls alias into two lobes a few degrees either side of the true direction
    half = len(_ANGLE_KERNEL) // 2
    smooth = np.convolve(np.concatenate([hist[-half:], hist, hist[:half]]), _ANGLE_KERNEL, mode="valid")
    ring = np.concatenate([smooth[-1:], smooth, smooth[:1]])  # np.roll by 1 and -1, as slices
    is_peak = (smooth >= ring[:-2]) & (smooth > ring[2:])
    peaks = np.flatnonzero(is_peak)
    peaks = peaks[np.argsort(-smooth[peaks], kind="stable")].tolist()
    out: list[float] = []
    for i in peaks[:max_peaks]:
        if out and smooth[i] < rel * smooth[peaks[0]]:
            break
        centre = (i + 0.5) / bins * 2 * np.pi
        d, wn = _near_turns(a4, centre, w)
        mean = centre + (np.sum(wn * d) / max(np.sum(wn), 1e-12))
        ang = float(np.angle(np.exp(1j * mean)) / 4.0)
        if all(abs(np.angle(np.exp(4j * (ang - o)))) > np.radians(80.0) for o in out):  # 20° apart
            out.append(ang)
    return out or [0.0]


# the circular histogram's smoothing kernel (bins of the 4x angle, σ = 12 bins, ±36)
_ANGLE_KERNEL = np.exp(-0.5 * (np.arange(-36, 37) / 12.0) ** 2)

# how far (radians of the 4x angle) an angle's difference is kept by :func:`_near_turns` before
# it is wrapped: the ±40° it keeps, and a margin far beyond the wrap's rounding
_NEAR = np.radians(40.0)
_NEAR_PRE = np.radians(45.0)


def _near_turns(a4: np.ndarray, centre: float, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The differences ``d = np.angle(np.exp(1j * (a4 - centre)))`` (wrapped to (-pi, pi]) within
    ±40° (``np.abs(d) < np.radians(40.0)``), in order, and their weights ``w``: ``d[near]``,
    ``w[near]``, with the complex exponential taken only where the raw difference (``a4`` and
    ``centre`` in [0, 2 pi]) is within 45° of a multiple of 2 pi (elsewhere the wrapped
    difference is more than 40°: the same elements, the same values)."""
    raw = a4 - centre
    mag = np.abs(raw)
    cand = np.flatnonzero((mag < _NEAR_PRE) | (mag > 2 * np.pi - _NEAR_PRE))
    d = np.angle(np.exp(1j * raw.take(cand)))
    near = np.abs(d) < _NEAR
    return d[near], w.take(cand)[near]


def lookup(img: np.ndarray, x: np.ndarray, y: np.ndarray, resolution: float, origin, fill) -> np.ndarray:
    """Nearest-cell values of ``img`` (row 0 = lowest y; uint8 or float32) at metric points
    (x, y arrays of one shape, at most 32767 wide); ``fill`` outside (cv2.remap)."""
    return lookups(((img, fill),), x, y, resolution, origin)[0]


def lookups(imgs, x: np.ndarray, y: np.ndarray, resolution: float, origin) -> list[np.ndarray]:
    """:func:`lookup` of several (image, fill) pairs of one raster frame at the same points (the
    cell coordinates computed once)."""
    shape = x.shape
    if x.size == 0:
        return [np.full(shape, fill, dtype=img.dtype) for img, fill in imgs]
    x2 = x.reshape(shape[0], -1) if x.ndim == 2 else x.reshape(1, -1)
    y2 = y.reshape(x2.shape)
    inv = np.float32(1.0 / resolution)
    half = np.float32(0.5)
    # (x - origin) * inv - 0.5 in place: the same dtypes and roundings, fewer temporaries
    mx = _scaled(x2, origin[0], inv)
    mx -= half
    my = _scaled(y2, origin[1], inv)
    my -= half
    mx = mx.astype(np.float32, copy=False)
    my = my.astype(np.float32, copy=False)
    return [
        cv2.remap(
            img, mx, my, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=float(fill)
        ).reshape(shape)
        for img, fill in imgs
    ]


def _scaled(v: np.ndarray, o: float, inv: np.float32) -> np.ndarray:
    """``(v - np.float32(o)) * inv`` as a new array; without the subtraction when ``o`` is +0.0
    (``v - 0.0`` is ``v`` for every float, -0.0 and NaN included)."""
    if o == 0.0 and math.copysign(1.0, o) > 0:
        return v * inv
    out = v - np.float32(o)
    out *= inv
    return out


def apply_affine(a: np.ndarray, t: np.ndarray, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(H, 2, 2), (H, 2) affine maps applied to (P, 2) points: x, y arrays of shape (H, P)."""
    a = a.astype(np.float32)
    t = t.astype(np.float32)
    p = pts.astype(np.float32)
    # the columns contiguous (unit-stride broadcasts): the same element operations
    px, py = np.ascontiguousarray(p[:, 0])[None], np.ascontiguousarray(p[:, 1])[None]
    # a00 * px + a01 * py + t0, left to right, in place (float32 roundings unchanged)
    x = a[:, 0, 0, None] * px
    x += a[:, 0, 1, None] * py
    x += t[:, 0, None]
    y = a[:, 1, 0, None] * px
    y += a[:, 1, 1, None] * py
    y += t[:, 1, None]
    return x, y
