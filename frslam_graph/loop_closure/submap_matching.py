"""Scan-to-submap matching for loop closure (points in metres, poses x, y, theta in radians).

:func:`match_scan` matches a *query* submap (points in the query keyframe's frame) against a
:class:`ReferenceSubmap` (points of a reference keyframe's neighbours, in its frame) around a
predicted pose. A correlative grid search over (x, y, theta) scores every pose at once
(vectorised over poses × points) on a likelihood field of the reference
(``cv2.distanceTransform``), max-filtered so the coarse grid cannot step over the peak; the best
distinct peaks are refined by point-to-line ICP on the reference points. The result
(:class:`ScanMatch`) carries the inlier fraction, the ambiguity (best distinct second peak over
the best), the ICP covariance and the share of query points in space the reference saw free;
:mod:`frslam_graph.loop_closure.closer` decides on it. :func:`match_scan_steps` is the same work as
bounded steps, each announcing its estimated cost (:mod:`frslam_graph.steps`).
"""

from __future__ import annotations

import ctypes
import math
import sys
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import TypeVar

import cv2
import numpy as np
from numpy.lib.stride_tricks import as_strided
from scipy.spatial import cKDTree

from frslam_graph.config import LoopClosureConfig
from frslam_graph.libc import libc_function
from frslam_graph.steps import Steps, run_steps

# Fixed settings (config fields until issue 20; never changed by a test, tool or doc):
COARSE_STEP_XY = 0.3  # m; translation step of the coarse correlative search; larger = faster, may miss peaks
COARSE_STEP_THETA_DEG = 1.5  # deg; heading step of the coarse search
MAX_QUERY_POINTS = 150  # query points sampled for the coarse search; larger = slower, surer
ICP_ITERATIONS = 10  # ICP refinement iterations per peak
ICP_MAX_DISTANCE = 0.5  # m; ICP correspondence distance at most
INLIER_DISTANCE = 0.1  # m; a query point this close to the reference is an inlier
REFINE_RATIO = 0.7  # other coarse peaks above this times the best are refined too (ambiguity)
PEAK_SEPARATION_XY = 1.0  # m; peaks closer than this (and in heading) are one peak
PEAK_SEPARATION_THETA_DEG = 10.0  # deg; heading part of peak separation
# likelihood-field look-ups per correlative-search step at most; larger = fewer, longer steps
MAX_LOOKUPS_PER_STEP = 300_000
ICP_SIGMA = 0.05  # m; point-to-line sigma of the closure covariance; larger = closures trusted less
MIN_COARSE_SCORE = 0.62  # below this coarse score: rejected without ICP; larger = fewer refinements

T = TypeVar("T")

# Cost model: milliseconds on one core of the development machine (2-core x86 VM, 2020s); only
# needs to be right within a factor of about two. Fitted to the measured medians per step on ACES
# (180 beams) and regime-A houses (720 beams, 30 m; tools/bench_backend.py) as the geometric mean
# of the two ratios (before: the ICP, field and free-space steps took 2-3.5x their estimate on
# the houses, so a scan's 8 ms budget ran 15-30 ms of closure work).
_MS_PER_LOOKUP = 4.3e-6  # correlative search: one likelihood-field look-up (gather + mean)
_MS_PER_CELL_FIELD = 3.3e-5  # reference submap: distance transform with labels + field, per inner cell
_MS_PER_CELL_FILL = 2.3e-6  # zero padding of the whole grid
_MS_PER_CELL_DILATE = 3e-6  # max filter of the field (first use of a step size)
_MS_PER_CELL_NEAREST = 3.6e-6  # nearest-point map for ICP, per cell
_MS_PER_CELL_FREE = 6.5e-6  # free-space mask, per cell
_MS_PER_POINT_NORMALS = 1.8e-3  # k-d tree and PCA normals, per reference point
_MS_ICP = 1.1  # one ICP refinement: fixed part ...
_MS_PER_POINT_ICP = 3.7e-4  # ... and per query point and iteration
_MS_FINE = 2.3  # finer level of the correlative search (a few hundred poses)


_EPS_EYE = 1e-9 * np.eye(3)  # regularises the ICP's normal equations


def _wrap(a):
    return (np.asarray(a) + np.pi) % (2.0 * np.pi) - np.pi


_SCRATCH = threading.local()


def _scratch(slot: int, shape: tuple[int, ...], dtype: type) -> np.ndarray:
    """An array of ``shape`` / ``dtype`` (C order, contents undefined) in this thread's buffer
    ``slot``, kept between calls and grown to the largest request: the large temporaries of
    the correlative search, the field build and the max filter. A fresh block of 256 kB or more
    is mapped anew and unmapped when freed (the pinned mmap threshold,
    :func:`frslam_graph.offline._pin_mmap_threshold`), and the kernel zero-fills each of its
    4 kB pages on first touch: FR079's backend took 4.3 million page faults (5.5-5.9 s of system
    CPU), 2.2-2.5 million with these buffers. A buffer of a slot is reused by the next call: a
    caller keeps no view of one past its own return (nor across a step's yield)."""
    bufs: dict[int, np.ndarray] | None = getattr(_SCRATCH, "bufs", None)
    if bufs is None:
        bufs = _SCRATCH.bufs = {}
    n = math.prod(shape) * np.dtype(dtype).itemsize
    buf = bufs.get(slot)
    if buf is None or buf.nbytes < n:
        buf = bufs[slot] = np.empty(n, np.uint8)
    return buf[:n].view(dtype).reshape(shape)


def _blank_grid(n: int) -> np.ndarray:
    """This thread's int32 grid of at least ``n`` cells, all -1 (a caller sets the cells it uses
    and sets them back to -1 before it returns); grown to the largest request."""
    grid: np.ndarray | None = getattr(_SCRATCH, "blank", None)
    if grid is None or len(grid) < n:
        grid = _SCRATCH.blank = np.full(n, -1, np.int32)
    return grid


# a block of the pool goes to a request of at least 1 / _POOL_SLACK of its size (its whole pages
# past the request are given back to the kernel: GridPool.take); 1.25 reused 42 % of FR079's
# requests, 2 79 %
_POOL_SLACK = 2.0
_PAGE = 4096  # bytes
# bytes of the correlative search's block gathers at most (below the pinned mmap threshold,
# offline.MMAP_THRESHOLD: from the heap)
_GATHER_BYTES = 192 << 10
_MADV_DONTNEED = 4  # madvise(2): the pages are dropped; zero-filled again on the next touch


def _dontneed() -> Callable[[int, int], object] | None:
    """Linux's ``madvise(addr, length, MADV_DONTNEED)``, or None elsewhere."""
    fn = libc_function("madvise", [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int], ctypes.c_int)
    return None if fn is None else lambda addr, length: fn(addr, length, _MADV_DONTNEED)


_POOLED_BYTES = 256 << 10  # smaller arrays come from the heap (no fresh mapping): not pooled


class GridPool:
    """The large arrays of reference submaps the loop closer dropped (likelihood field, labels
    and nearest-point map on the inner grid; max-filtered fields on the whole grid: 0.5-2 MB
    each at 5 cm), handed to its next submaps instead of fresh ones.

    Under the pinned mmap threshold (:func:`frslam_graph.offline._pin_mmap_threshold`) a fresh
    array is a new mapping whose every 4 kB page the kernel zero-fills on first touch: FR079's
    backend took ~1.9 million page faults, most in submap builds. A pooled block is resident
    already; every array taken from it is written whole (a max-filtered field's margin is set
    to zero) and the block's whole pages past it are dropped (``madvise(MADV_DONTNEED)``), so it
    holds no more memory than a fresh one once that one is written. Best fit, within
    ``_POOL_SLACK`` of the request; at most ``capacity`` blocks wait (the oldest freed)."""

    def __init__(self, capacity: int = 8):
        self.capacity = capacity
        self._blocks: list[np.ndarray] = []  # 1-D uint8, oldest first
        self._dontneed = _dontneed()
        self.reused = 0  # arrays handed out of the pool (tests, tools)
        self.kept = 0  # blocks taken in

    def take(self, shape: tuple[int, ...], dtype: type) -> np.ndarray | None:
        """A C-order array of ``shape`` / ``dtype`` (contents undefined) on a pooled block, or
        None when no block fits."""
        n = math.prod(shape) * np.dtype(dtype).itemsize
        best = -1
        for i, b in enumerate(self._blocks):
            if n <= b.nbytes <= _POOL_SLACK * n and (best < 0 or b.nbytes < self._blocks[best].nbytes):
                best = i
        if best < 0:
            return None
        self.reused += 1
        block = self._blocks.pop(best)
        if self._dontneed is not None:  # the whole pages past the request: not held for nothing
            start = block.__array_interface__["data"][0]
            lo, hi = -(-(start + n) // _PAGE) * _PAGE, (start + block.nbytes) // _PAGE * _PAGE
            if hi > lo:
                self._dontneed(lo, hi - lo)
        return block[:n].view(dtype).reshape(shape)

    def put(self, a: np.ndarray) -> None:
        """Keep the block under ``a``, an array the caller hands over holding no reference to
        it (``pool.put(arrays.pop())``), unless another array or view still refers to it (a
        suspended match's look-ups): then it is left to be freed."""
        # references: this frame's `a` and getrefcount's argument; a view's block also a's base
        # and `block`
        if sys.getrefcount(a) > 2:
            return
        block = a if a.base is None else a.base
        if block is not a and sys.getrefcount(block) > 3:
            return
        if not isinstance(block, np.ndarray) or not block.flags.c_contiguous or block.nbytes < _POOLED_BYTES:
            return
        self._blocks.append(block.reshape(-1).view(np.uint8))
        self.kept += 1
        if len(self._blocks) > self.capacity:
            self._blocks.pop(0)


def transform_points(pose: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Points (M, 2) given in the frame ``pose`` (x, y, theta) -> the frame ``pose`` lives in."""
    return rigid_points(
        pose[0], pose[1], np.cos(pose[2]), np.sin(pose[2]), np.asarray(points, dtype=np.float64)
    )


def rigid_points(x, y, c, s, p: np.ndarray) -> np.ndarray:
    """(x, y) + R(c, s) p for points p (M, 2); x, y, c, s scalars or (M,) per point."""
    px, py = p[:, 0], p[:, 1]
    out = np.empty((len(p), 2))  # as np.column_stack of the two columns, without its copies
    out[:, 0] = x + c * px - s * py
    out[:, 1] = y + s * px + c * py
    return out


def point_bounds(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-axis (min, max) of (M, 2) points, M >= 1. Column by column: numpy's axis-0 reduction
    of an (M, 2) array is ~50x slower (two-element inner loops)."""
    return (
        np.array([points[:, 0].min(), points[:, 1].min()]),
        np.array([points[:, 0].max(), points[:, 1].max()]),
    )


def stable_order(key: np.ndarray) -> np.ndarray:
    """``np.argsort(key, kind="stable")`` of an int64 array (N,), the same indices, ~3x faster:
    each key and its index packed into one int64 (key - min above the index's bits) and sorted
    by value. Keys spanning too wide a range for that are argsorted."""
    n = len(key)
    if n == 0:
        return np.zeros(0, np.intp)
    lo = int(key.min())
    bits = max(int(n - 1).bit_length(), 1)
    if int(key.max()) - lo >= 1 << (62 - bits):
        return np.argsort(key, kind="stable")
    packed = ((key - lo) << bits) | np.arange(n, dtype=np.int64)
    packed.sort()  # in place: np.sort's copy of a temporary
    return (packed & ((1 << bits) - 1)).astype(np.intp)


def first_of_each(key: np.ndarray) -> np.ndarray:
    """``np.unique(key, return_index=True)[1]`` of an int64 array (N,), N >= 1: the index of each
    distinct key's first occurrence, in key order."""
    order = stable_order(key)
    ks = key[order]
    first = np.empty(len(ks), bool)
    first[0] = True
    np.not_equal(ks[1:], ks[:-1], out=first[1:])
    return order[first]


def voxel_downsample(points: np.ndarray, voxel: float) -> np.ndarray:
    """The first point of each occupied voxel (order kept)."""
    if len(points) == 0:
        return np.zeros((0, 2))
    cells = np.floor(points / voxel).astype(np.int64)
    h = cells[:, 0] * 73856093 ^ cells[:, 1] * 19349663
    return points.take(np.sort(first_of_each(h)), axis=0)


def cell_means(points: np.ndarray, cell: float) -> np.ndarray:
    """The mean of the points in each occupied ``cell`` × ``cell`` square (m), in cell order.

    Overlaid noisy scans of a wall become one point per cell on the wall's centre line, so the
    normals fitted to nearest neighbours run across the wall and not along the noise."""
    if len(points) == 0:
        return np.zeros((0, 2))
    # column by column: numpy's axis-0 reductions of an (M, 2) array are ~50x slower
    x, y = np.ascontiguousarray(points[:, 0]), np.ascontiguousarray(points[:, 1])
    i, j = np.floor(x / cell).astype(np.int64), np.floor(y / cell).astype(np.int64)
    i -= i.min()
    j -= j.min()
    key = i * (int(j.max()) + 1) + j
    # np.unique(key, return_inverse=True, return_counts=True), two thirds cheaper
    order = stable_order(key)
    ks = key[order]
    first = np.empty(len(ks), bool)
    first[0] = True
    np.not_equal(ks[1:], ks[:-1], out=first[1:])
    inv = np.empty(len(ks), np.intp)
    inv[order] = first.cumsum() - 1
    bounds = np.concatenate((first.nonzero()[0], [len(ks)]))
    count = bounds[1:] - bounds[:-1]  # np.diff
    n = len(count)  # bincount adds in point order, as np.add.at did (same sums, 3x faster)
    out = np.empty((n, 2))  # as np.column_stack of the two means, without its copies
    out[:, 0], out[:, 1] = np.bincount(inv, x, n) / count, np.bincount(inv, y, n) / count
    return out


def _normals(
    points: np.ndarray, tree: cKDTree, k: int = 6, at: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals (N, 2) from PCA of the k nearest neighbours, and a line-quality weight (N,);
    ``at``: indices of the points to compute them for (default all; each point's are the same
    either way)."""
    k = min(k, len(points))
    q = points if at is None else points.take(at, axis=0)
    _, nn = tree.query(q, k=k)
    nb = points.take(nn.reshape(len(q), k), axis=0)  # (N, k, 2); rows by take: ~10x faster
    m = nb[:, 0].copy()
    for i in range(1, k):  # the neighbours' mean, summed in order as nb.mean(axis=1) (3x faster)
        m += nb[:, i]
    d = nb - (m / k)[:, None, :]
    sxx = np.einsum("ij,ij->i", d[:, :, 0], d[:, :, 0])
    syy = np.einsum("ij,ij->i", d[:, :, 1], d[:, :, 1])
    sxy = np.einsum("ij,ij->i", d[:, :, 0], d[:, :, 1])
    # smallest eigenvalue / eigenvector of [[sxx, sxy], [sxy, syy]] in closed form
    tr, det = sxx + syy, sxx * syy - sxy**2
    disc = np.sqrt(np.maximum(tr**2 / 4.0 - det, 0.0))
    lmin, lmax = tr / 2.0 - disc, tr / 2.0 + disc
    n, alt = np.empty((len(q), 2)), np.empty((len(q), 2))  # as np.column_stack, without its copies
    n[:, 0], n[:, 1] = sxy, lmin - sxx
    alt[:, 0], alt[:, 1] = lmin - syy, sxy
    use_alt = np.hypot(*n.T) < np.hypot(*alt.T)
    np.copyto(n, alt, where=use_alt[:, None])  # n[use_alt] = alt[use_alt]
    norm = np.hypot(*n.T)
    degenerate = norm < 1e-12
    n[degenerate] = (1.0, 0.0)
    n /= np.maximum(np.hypot(*n.T), 1e-12)[:, None]
    quality = np.where(lmax > 1e-12, 1.0 - np.clip(lmin / np.maximum(lmax, 1e-12), 0.0, 1.0), 0.0)
    quality[degenerate] = 0.0
    return n, quality


# ----------------------------------------------------------------------------- reference submap
class ReferenceSubmap:
    """Points of a reference submap with a likelihood field (correlative search) and a k-d tree
    with normals (ICP). ``points`` (M, 2) in the reference keyframe's frame.

    The likelihood field is built on construction; what only ICP and the free-space test need
    (nearest point per cell, normals, the free-space mask) is built on first use, so a candidate
    rejected by the correlative search never pays for it (and the anytime matcher can build it in
    a step of its own)."""

    @staticmethod
    def build_cost(points: np.ndarray, resolution: float, sigma: float, margin: float) -> float:
        """Estimated cost (ms) of building a submap of ``points`` (M >= 1) with these arguments:
        the distance transform over the inner cells and the zero padding of the whole grid."""
        inner = min(margin, max(16.0 * sigma, 2.0))  # as __init__
        lo, hi = point_bounds(points)
        extent = hi - lo
        cells = np.prod((extent + 2.0 * margin) / resolution + 1.0)
        cells_inner = np.prod((extent + 2.0 * inner) / resolution + 1.0)
        return _MS_PER_CELL_FIELD * float(cells_inner) + _MS_PER_CELL_FILL * float(cells)

    def __init__(
        self,
        points: np.ndarray,
        resolution: float,
        sigma: float,
        margin: float,
        scans: list[tuple[np.ndarray, np.ndarray]] | None = None,
        free_margin: float = 0.3,
        likelihood: bool = True,
        pool: GridPool | None = None,
    ):
        """``likelihood`` False: no likelihood field (``field`` None; for ICP and inlier tests
        only, which need the nearest-point map alone). ``pool``: where its large arrays come
        from when it has one that fits (:class:`GridPool`; the same values either way)."""
        self._pool = pool
        pts = voxel_downsample(np.asarray(points, dtype=np.float64), resolution)
        self.points = pts
        self.resolution = res = float(resolution)
        lo, hi = point_bounds(pts) if len(pts) else (np.zeros(2), np.zeros(2))
        lo, hi = lo - margin, hi + margin
        self.origin = lo
        self.margin_cells = int(np.ceil(margin / res))
        w, h = (np.ceil((hi - lo) / res).astype(int) + 1).tolist()
        self.shape = (h, w)
        # Distances are computed on an inner grid only (the points' box + max(16 sigma, 2 m)):
        # farther out the float32 likelihood is exactly 0 (it underflows beyond 14.4 sigma), no
        # nearest point is within 2 m and every cell is far from the end points. The outer
        # margin (for the correlative search's clamped look-ups) is zero padding.
        pad = max(0, int(np.floor((margin - max(16.0 * sigma, 2.0)) / res)))
        pad = min(pad, (h - 1) // 2, (w - 1) // 2)
        hi_, wi = h - 2 * pad, w - 2 * pad
        self._inner = (pad, hi_, wi)
        free = _scratch(0, (hi_, wi), np.uint8)  # a scratch buffer (_scratch): only its zeros are kept
        free.fill(255)
        self._cells = np.zeros(0, np.int64)  # flat index of each point's cell (full grid)
        if len(pts):
            ij = np.floor((pts - lo) / res).astype(int)
            free[ij[:, 1] - pad, ij[:, 0] - pad] = 0
            self._cells = ij[:, 1] * w + ij[:, 0]
        # distances (5×5 mask, within about 2 %) and the nearest occupied cell of every cell
        dist, self._labels = cv2.distanceTransformWithLabels(
            free,
            cv2.DIST_L2,
            cv2.DIST_MASK_5,
            labelType=cv2.DIST_LABEL_PIXEL,
            dst=_scratch(1, free.shape, np.float32),
            labels=self._take(free.shape, np.int32),
        )
        dist *= res
        self._occupied = free.ravel() == 0  # inner grid
        self._scans = scans
        # Kept on the inner grid only (the margin's values are implied: likelihood 0, no
        # nearest point, far from every end point): a full-grid array is a fresh mapping whose
        # pages the kernel zero-fills as they are first touched, ~1,500 per submap on FR079.
        # free space must be farther than free_margin from any end point (inner grid)
        self._far = dist > free_margin if scans else None
        #: the likelihood field on the inner grid (hi_, wi) float32 (0 beyond it), or None
        self.field: np.ndarray | None = None
        if likelihood:  # exp(-0.5 (dist / sigma)²), in place (dist is not needed after it)
            lik = np.divide(dist, sigma, out=dist)
            np.square(lik, out=lik)
            lik *= -0.5
            self.field = np.exp(lik, out=self._take(lik.shape, np.float32))
        self._nearest: np.ndarray | None = None
        self._tree: cKDTree | None = None
        self._normals: tuple[np.ndarray, np.ndarray] | None = None
        self._free: np.ndarray | None = None
        self._free_costed = False  # the matcher announced the free-space mask's step
        self._dilated: dict[int, np.ndarray] = {}

    # ----- built on first use (ICP, free-space test)
    def _take(self, shape: tuple[int, ...], dtype: type) -> np.ndarray | None:
        """An array from the pool (contents undefined), or None (then a fresh one is made)."""
        return None if self._pool is None else self._pool.take(shape, dtype)

    def release(self) -> None:
        """Hand the large arrays to the pool when the caller drops this submap and holds no
        reference to it (``submaps.pop().release()``); a submap still referenced elsewhere (a
        suspended match) keeps them."""
        # this call's `self` and getrefcount's argument
        if self._pool is None or sys.getrefcount(self) > 2:
            return
        arrays = [
            a for a in (self.field, self._labels, self._nearest, *self._dilated.values()) if a is not None
        ]
        self.field = self._labels = self._nearest = None
        self._dilated = {}
        while arrays:
            self._pool.put(arrays.pop())

    @property
    def inner_grid(self) -> tuple[int, int, int]:
        """(pad, rows, cols): the inner grid, ``pad`` cells in from the whole grid's origin, on
        which :attr:`field` and :attr:`nearest` are kept."""
        return self._inner

    def padded(self, inner: np.ndarray, fill: float | bool) -> np.ndarray:
        """An inner-grid array (:attr:`field`, :attr:`nearest`) laid on the whole grid
        (``shape``, flattened), ``fill`` in the margin (0, -1): what it stands for."""
        pad, hi_, wi = self._inner
        out = np.full(self.shape, fill, inner.dtype)
        out[pad : pad + hi_, pad : pad + wi] = inner.reshape(hi_, wi)
        return out.ravel()

    @property
    def nearest(self) -> np.ndarray:
        """Index of the nearest reference point of every cell of the inner grid (``_inner``;
        flattened; -1 without points; the margin has none: :meth:`padded`)."""
        if self._nearest is None:
            w = self.shape[1]
            pad, hi_, wi = self._inner
            if not len(self.points):
                nearest = np.full(hi_ * wi, -1, np.int32)
            else:
                # the reference point in each occupied cell (the last one in it), on the inner
                # grid, where every point lies, in a scratch buffer (_scratch): only the occupied
                # cells are read, and each was written (a full-grid table and three inner-grid
                # temporaries were fresh mappings whose pages the kernel zero-filled: FR079's
                # backend took 0.8 million page faults here)
                owner = _scratch(0, (hi_ * wi,), np.int32)
                inner_cells = self._cells - (pad * w + pad)  # full-grid flat -> inner-grid flat
                owner[(inner_cells // w) * wi + inner_cells % w] = np.arange(len(self.points), dtype=np.int32)
                # labels number the (inner grid's) zero cells in raster order from 1: the table's
                # entry 0 is entry 1 (as the clipped look-up of label - 1 gave)
                occupied = np.flatnonzero(self._occupied)
                table = np.empty(len(occupied) + 1, np.int32)
                table[1:] = owner[occupied]
                table[0] = table[1]
                labels = self._labels.ravel()
                nearest = np.take(table, labels, out=self._take(labels.shape, np.int32), mode="clip")
                del labels
            self._nearest = nearest
            done = [self._labels]  # handed to the pool without a reference left here
            self._labels = None
            if self._pool is not None and done[0] is not None:
                self._pool.put(done.pop())
        return self._nearest

    @property
    def tree(self) -> cKDTree | None:
        if self._tree is None and len(self.points):
            self._tree = cKDTree(self.points)
        return self._tree

    def _normals_quality(self) -> tuple[np.ndarray, np.ndarray]:
        if self._normals is None:
            n = len(self.points)
            self._normals = _normals(self.points, self.tree) if n >= 3 else (np.zeros((n, 2)), np.zeros(n))
        return self._normals

    @property
    def normals(self) -> np.ndarray:
        return self._normals_quality()[0]

    @property
    def quality(self) -> np.ndarray:
        return self._normals_quality()[1]

    @property
    def free(self) -> np.ndarray | None:
        """Cells the reference scans saw free (sensor -> end points polygons) away from any end
        point (flattened bool), or None without scans: a query point there contradicts the match."""
        if self._free is None and self._scans:
            h, w = self.shape
            seen = np.zeros((h, w), np.uint8)
            scans = [(o, e) for o, e in self._scans if len(e) >= 2]
            if scans:  # each polygon: sensor origin, then the end points; all rounded at once
                ij = np.round(
                    (np.vstack([np.vstack((o[None], e)) for o, e in scans]) - self.origin) / self.resolution
                )
                polys = np.split(ij.astype(np.int32), np.cumsum([len(e) + 1 for _, e in scans])[:-1])
                cv2.fillPoly(seen, polys, 1)
            free = seen > 0
            pad, hi_, wi = self._inner
            free[pad : pad + hi_, pad : pad + wi] &= self._far  # beyond the inner grid: far
            self._free = free.ravel()
        return self._free

    def prepare_icp(self) -> None:
        """Build what ICP and its inlier test need now (k-d tree, normals, nearest-point map)."""
        self.nearest  # noqa: B018
        self._normals_quality()

    def exact_nearest_offsets(
        self, points: np.ndarray, max_distance: float
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """ICP's correspondences: (indices into ``points`` with a reference point within
        max_distance, the exact nearest reference point's index (k-d tree), those points, and
        their offsets ``points[sel] - self.points[j]``). The cell look-up of
        :meth:`nearest_points` answers with the one point kept for the nearest occupied cell,
        which on a noisy wall (a band of cells) sits on the band's edge facing the query, with
        ties broken in raster order: a bias of a few millimetres along the grid's axes. Scan-to-local-map odometry accumulates it (simulated 3 cm noise: 2 mm per
        scan even standing still, metres over a run); the exact neighbour has none."""
        return _exact_nearest_offsets(self.tree, self.points, points, max_distance)

    def line_normals(self, j: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Normals (len(j), 2) and line qualities (len(j),) of the reference points ``j``."""
        return self.normals[j], self.quality[j]

    def correspondences(self, start: np.ndarray, max_distance: float) -> ReferenceSubmap:
        """ICP's nearest reference points for query points starting at ``start`` (N, 2): the
        submap itself (:meth:`exact_nearest_offsets`). The loop-closure matcher starts at a
        correlative-search peak and moves centimetres per iteration, so each iteration asks the
        k-d tree (:class:`_NearestCandidates` was slower there: FR079 1.63 -> 1.75 ms per ICP)."""
        return self

    def nearest_points(self, points: np.ndarray, max_distance: float) -> tuple[np.ndarray, np.ndarray]:
        """(indices into ``points`` with a reference point within max_distance, those reference
        points' indices): nearest neighbours by a cell look-up (exact up to one cell; for
        counting inliers, not for ICP's correspondences: see :meth:`exact_nearest_offsets`)."""
        pad, h, w = self._inner  # the nearest-point map's grid: beyond it no point is near
        ix = np.floor((points[:, 0] - self.origin[0]) / self.resolution).astype(np.int64)
        iy = np.floor((points[:, 1] - self.origin[1]) / self.resolution).astype(np.int64)
        if pad:
            ix -= pad
            iy -= pad
        inside = (ix >= 0) & (ix < w) & (iy >= 0) & (iy < h)
        if inside.all():  # usual: the inner grid holds the query (no gathers then)
            sel, ps, flat = np.arange(len(points)), points, iy * w + ix
        else:
            sel = np.flatnonzero(inside)
            ps, flat = points[sel], iy[sel] * w + ix[sel]
        j = self.nearest[flat]
        off = ps - self.points[np.maximum(j, 0)]
        ok = np.flatnonzero((j >= 0) & (np.hypot(off[:, 0], off[:, 1]) <= max_distance))
        return sel[ok], j[ok]

    def dilated(self, cells: int) -> np.ndarray:
        """The likelihood field max-filtered over a (2·cells + 1)² window (flattened)."""
        f = self._dilated.get(cells)
        if f is None:
            if cells > 0:
                # beyond `cells` of the inner grid the field is zero padding, and stays zero
                h, w = self.shape
                pad, hi_, wi = self._inner
                r0, r1 = max(pad - cells, 0), min(pad + hi_ + cells, h)
                c0, c1 = max(pad - cells, 0), min(pad + wi + cells, w)
                kernel = np.ones((2 * cells + 1, 2 * cells + 1), np.uint8)
                f = self._take((h, w), np.float32)
                if f is None:
                    f = np.zeros((h, w), np.float32)
                else:  # a pooled block: zeros where the max filter does not write
                    f[:r0] = 0.0
                    f[r1:] = 0.0
                    f[r0:r1, :c0] = 0.0
                    f[r0:r1, c1:] = 0.0
                # the block (the inner grid's field in its zero ring) and its max filter in
                # scratch buffers (_scratch), the result kept
                src = _scratch(0, (r1 - r0, c1 - c0), np.float32)
                src.fill(0.0)
                src[pad - r0 : pad - r0 + hi_, pad - c0 : pad - c0 + wi] = self.field
                f[r0:r1, c0:c1] = cv2.dilate(src, kernel, dst=_scratch(1, src.shape, np.float32))
                f = f.ravel()
            else:
                f = self.padded(self.field, 0.0)
            self._dilated[cells] = f
        return f

    def free_violation(self, query: np.ndarray, pose: np.ndarray) -> float:
        """Share of query points (at ``pose``) in space the reference saw free (0 without scans)."""
        if self.free is None or len(query) == 0:
            return 0.0
        h, w = self.shape
        ij = np.floor((transform_points(pose, query) - self.origin) / self.resolution).astype(np.int64)
        inside = (ij[:, 0] >= 0) & (ij[:, 0] < w) & (ij[:, 1] >= 0) & (ij[:, 1] < h)
        return float(self.free[ij[inside, 1] * w + ij[inside, 0]].sum()) / len(query)

    def inlier_fraction(self, query: np.ndarray, pose: np.ndarray, distance: float) -> float:
        if len(self.points) == 0 or len(query) == 0:
            return 0.0
        sel, _ = self.nearest_points(transform_points(pose, query), distance)
        return len(sel) / len(query)


def _exact_nearest_offsets(
    tree: cKDTree | None, ref_points: np.ndarray, points: np.ndarray, max_distance: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:meth:`ReferenceSubmap.exact_nearest_offsets` on a k-d tree over ``ref_points``."""
    if tree is None or len(points) == 0:
        e = np.zeros(0, np.int64)
        return e, e, np.zeros((0, 2)), np.zeros((0, 2))
    d, j = tree.query(points, distance_upper_bound=max_distance)
    sel = np.isfinite(d).nonzero()[0]
    j = j[sel]
    ps = points.take(sel, axis=0)  # rows by take, not points[sel]: the same copy, ~4x faster
    return sel, j, ps, ps - ref_points.take(j, axis=0)


class _NearestCandidates:
    """Exact nearest reference points of query points that move a little: ICP's iterations.

    A k-d tree query costs ~100 us for a scan's few hundred points, six times per scan in the
    odometry's refinement. Its answers are kept from one query, at the query points' first
    positions ``start`` (N, 2): their ``k`` nearest reference points within ``reach`` (m). A
    point that has since moved by delta is at least ``bound - delta`` from every reference point
    outside its ``k`` >= 2 candidates (``bound``: the k-th one's distance, ``reach`` when it has fewer);
    when its nearest candidate is nearer than that, with no tie (1e-9 m) with the next candidate,
    the bound or ``max_distance``, it is its exact nearest neighbour; when both are beyond
    ``max_distance``, it has none. The few points left undecided are asked to the tree: the same
    answers as :func:`_exact_nearest_offsets` on the tree, whatever the moves (tested)."""

    def __init__(self, tree: cKDTree, ref_points: np.ndarray, start: np.ndarray, reach: float, k: int):
        d, idx = tree.query(start, k=k, distance_upper_bound=reach)
        found = np.isfinite(d)
        self.tree, self.ref_points = tree, ref_points
        self.sx, self.sy = np.ascontiguousarray(start[:, 0]), np.ascontiguousarray(start[:, 1])
        self.bound = np.where(found[:, -1], d[:, -1], reach)
        idx = np.where(found, idx, 0)
        cx = np.where(found, ref_points[idx, 0], np.inf)  # missing candidates: infinitely far
        cy = np.where(found, ref_points[idx, 1], np.inf)
        # one row per rank (k, N): a rank's candidates of all points read as a contiguous vector
        self.idx, self.cx, self.cy = (np.ascontiguousarray(a.T) for a in (idx, cx, cy))
        given = np.zeros(len(ref_points), bool)
        given[idx[found]] = True
        self.indices = given.nonzero()[0]  # every reference point a query may be given

    def exact_nearest_offsets(
        self, points: np.ndarray, max_distance: float
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """As :func:`_exact_nearest_offsets` for ``points`` (N, 2): the start points moved."""
        px, py = points[:, 0], points[:, 1]
        dx = self.cx - px  # (k, N)
        d2 = np.multiply(dx, dx, out=dx)
        dy = self.cy - py
        d2 += np.multiply(dy, dy, out=dy)  # dx² + dy², as summed per element
        # the nearest and the next candidate's squared distances (exact: min / max select)
        m1, m2 = np.minimum(d2[0], d2[1]), np.maximum(d2[0], d2[1])
        for row in d2[2:]:
            m2 = np.minimum(m2, np.maximum(m1, row))
            m1 = np.minimum(m1, row)
        c, c2 = np.sqrt(m1), np.sqrt(m2)
        safe = self.bound - np.hypot(px - self.sx, py - self.sy) - _TIE
        near = (c < safe) & (c2 > c + _TIE)  # the nearest candidate is the nearest point
        sure = (near & (np.abs(c - max_distance) > _TIE)) | (
            (safe > max_distance + _TIE) & (c > max_distance + _TIE)
        )
        hit = sure & (c < max_distance)
        # a sure hit's nearest candidate is unique (near): the rank whose distance is the least
        j = self.idx[-1].copy()
        for r in range(len(d2) - 2, -1, -1):
            np.copyto(j, self.idx[r], where=d2[r] == m1)
        if not sure.all():
            ask = (~sure).nonzero()[0]
            d, jj = self.tree.query(points[ask], distance_upper_bound=max_distance)
            ok = np.isfinite(d)
            hit[ask] = ok
            j[ask[ok]] = jj[ok]
        sel = hit.nonzero()[0]
        j = j[sel]
        ps = points.take(sel, axis=0)
        return sel, j, ps, ps - self.ref_points.take(j, axis=0)


class LineMap:
    """Reference points (M, 2) with a k-d tree and line normals, no grid: for point-to-line ICP
    (:func:`icp_point_to_line`) and inlier counts only. The odometry's local map, rebuilt every
    scan, where :class:`ReferenceSubmap` (``likelihood=False``) spent most of its build on a
    distance transform of a ~30 m grid and on all its normals, for the few hundred points a scan
    meets.

    The same answers as ``ReferenceSubmap(points, resolution, sigma, margin, likelihood=False)``:
    the same points (the first per ``resolution`` voxel); correspondences by exact nearest
    neighbours; a point's normal computed the first time ICP matches it (the same values);
    :meth:`inlier_fraction` by the same cell look-up, on the occupied cells alone."""

    def __init__(self, points: np.ndarray, resolution: float, margin: float):
        self.points = pts = voxel_downsample(np.asarray(points, dtype=np.float64), resolution)
        self.resolution = float(resolution)
        self.margin = float(margin)
        self.tree: cKDTree | None = cKDTree(pts) if len(pts) else None
        self._normals = np.zeros((len(pts), 2))
        self._quality = np.zeros(len(pts))
        self._known = np.zeros(len(pts), bool)  # normal computed
        self._known[:] = len(pts) < 3  # too few points for a line: zero normals and quality
        self._grid_cells: tuple[np.ndarray, int, int, np.ndarray] | None = None

    def exact_nearest_offsets(
        self, points: np.ndarray, max_distance: float
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """As :meth:`ReferenceSubmap.exact_nearest_offsets`."""
        return _exact_nearest_offsets(self.tree, self.points, points, max_distance)

    def correspondences(self, start: np.ndarray, max_distance: float) -> _NearestCandidates:
        """ICP's nearest reference points for query points starting at ``start`` (N, 2): the
        odometry's refinement starts at KISS-ICP's pose and moves millimetres, so one query's
        candidates serve every iteration (:class:`_NearestCandidates`; FR079: 1.31 -> 1.05 ms
        per ICP); the normals they may need are computed in one batch."""
        near = _NearestCandidates(
            self.tree, self.points, start, max_distance + _CANDIDATE_MARGIN, _CANDIDATES
        )
        self.line_normals(near.indices)
        return near

    def line_normals(self, j: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Normals (len(j), 2) and line qualities (len(j),) of the reference points ``j``."""
        new = j[~self._known[j]]
        if len(new):
            ask = np.zeros(len(self.points), bool)
            ask[new] = True
            new = ask.nonzero()[0]  # np.unique(new)
            self._normals[new], self._quality[new] = _normals(self.points, self.tree, at=new)
            self._known[new] = True
        return self._normals.take(j, axis=0), self._quality[j]

    def _occupied(self) -> tuple[np.ndarray, int, int, np.ndarray, np.ndarray]:
        """ReferenceSubmap's grid, occupied cells only: origin (2,), width, height, the occupied
        cells and the point each keeps (the last one in it, as ``owner[cells] = arange`` keeps
        it). The cells are flat indices (raster order) of that grid with a border of one cell
        added all round (width + 2 columns): a look-up of a cell's neighbours never wraps to
        another row, and finds nothing on the border."""
        if self._grid_cells is None:
            pts, res = self.points, self.resolution
            lo, hi = point_bounds(pts)
            lo, hi = lo - self.margin, hi + self.margin
            w, h = (np.ceil((hi - lo) / res).astype(int) + 1).tolist()
            ij = np.floor((pts - lo) / res).astype(int)
            flat = ij[:, 1] * w + ij[:, 0]
            order = stable_order(flat)
            fs = flat[order]
            # the last point of each cell, as owner[cells] = arange
            last = np.concatenate((fs[1:] != fs[:-1], [True]))
            kept = order[last]
            bordered = (ij[kept, 1] + 1) * (w + 2) + ij[kept, 0] + 1
            self._grid_cells = (lo, w, h, bordered, kept.astype(np.int32))
        return self._grid_cells

    def inlier_fraction(self, query: np.ndarray, pose: np.ndarray, distance: float) -> float:
        """Share of ``query`` points (at ``pose``) within ``distance`` of the point their cell
        look-up answers with, as :meth:`ReferenceSubmap.inlier_fraction` (``distance`` at most
        ``resolution``): its distance transform labels a cell with its nearest occupied cell,
        itself, else an occupied side neighbour, else a corner one, ties broken as
        ``_CELL_ORDER`` lists them; a farther cell's point is farther than ``resolution``."""
        return float(self.inlier_fractions(query, [pose], distance)[0])

    def inlier_fractions(self, query: np.ndarray, poses: list[np.ndarray], distance: float) -> np.ndarray:
        """:meth:`inlier_fraction` of ``query`` at each of ``poses``, in one look-up (the
        refinement's test of its result against its start)."""
        if len(self.points) == 0 or len(query) == 0:
            return np.zeros(len(poses))
        return fractions_within(self.lookup_distances(query, poses), distance)

    def lookup_distances(self, query: np.ndarray, poses: list[np.ndarray]) -> np.ndarray:
        """(len(poses), N) distances (m) of the ``query`` points (N, 2; N >= 1) at each pose to
        the point their cell look-up answers with (:meth:`inlier_fraction`), inf where it
        answers none: :func:`fractions_within` of them at any distance is
        :meth:`inlier_fractions` (the odometry tests one pose at two distances). A non-empty map."""
        lo, w, h, cells, owners = self._occupied()
        p = np.concatenate([transform_points(pose, query) for pose in poses])
        ix = np.floor((p[:, 0] - lo[0]) / self.resolution).astype(np.int64)
        iy = np.floor((p[:, 1] - lo[1]) / self.resolution).astype(np.int64)
        inside = (ix >= 0) & (ix < w) & (iy >= 0) & (iy < h)  # the query's cell in the grid
        wb = w + 2  # the bordered grid's width (see _occupied); outside queries look in the corner
        at = np.where(inside, (iy + 1) * wb + (ix + 1), wb + 1)
        # the point per cell (-1: none) on a grid kept between calls, blank outside them: filling
        # a fresh one cost more than the look-ups (~1.5 MB, its pages zero-filled by the kernel)
        grid = _blank_grid(wb * (h + 2))
        grid[cells] = owners
        try:
            # the first cell of _CELL_ORDER holding a point (-1: none), taken from the last one back
            steps = [dy * wb + dx for dx, dy in _CELL_ORDER.tolist()]
            who = grid[at + steps[-1]]
            for step in steps[-2::-1]:
                there = grid[at + step]
                np.copyto(who, there, where=there >= 0)
        finally:
            grid[cells] = -1
        found = inside & (who >= 0)
        off = p - self.points.take(np.maximum(who, 0), axis=0)
        dist = np.hypot(off[:, 0], off[:, 1])
        np.copyto(dist, np.inf, where=~found)
        return dist.reshape(len(poses), len(query))


def fractions_within(distances: np.ndarray, distance: float) -> np.ndarray:
    """Share of each row of ``distances`` (P, N; N >= 1, m) at most ``distance`` (m): (P,)."""
    return np.count_nonzero(distances <= distance, axis=1) / distances.shape[1]


# icp_point_to_line's nearest neighbours (_NearestCandidates): candidates per query point, and
# reach beyond the association distance (m); more = fewer points asked to the tree again, a
# slower first query (FR079's refinement: 0.7 % asked again)
_CANDIDATES = 4
_CANDIDATE_MARGIN = 0.1
_TIE = 1e-9  # m; distances closer than this are a tie (asked to the tree), far above rounding

# LineMap.inlier_fraction's cells (dx, dy; dy -1 = the previous grid row): the query's own, the
# sides, the corners, in the order cv2.distanceTransformWithLabels (5×5 mask, one label per
# pixel) breaks ties among equally near occupied cells (found by trying all 255 neighbourhoods:
# tests/test_odometry_refine.py)
_CELL_ORDER = np.array([(0, 0), (0, -1), (-1, 0), (0, 1), (1, 0), (-1, -1), (1, -1), (1, 1), (-1, 1)])


# ----------------------------------------------------------------------------- matcher
@dataclass(frozen=True, slots=True)
class ScanMatch:
    """Result of :func:`match_scan`: the query frame's pose in the reference frame.

    ``inlier_fraction``: share of query points within ``INLIER_DISTANCE`` of the reference after
    ICP; ``ambiguity``: the best distinct second peak's inlier fraction / the best (0 = none);
    ``covariance``: 3×3 in GTSAM's Pose2 tangent (body frame of ``pose``).
    """

    pose: np.ndarray
    inlier_fraction: float
    ambiguity: float
    covariance: np.ndarray
    coarse_score: float
    n_points: int
    second: np.ndarray | None = None
    # share of query points in the reference's free space (NaN: not measured, the match has too
    # few inliers or is ambiguous for the closer to accept it)
    free_violation: float = 0.0


def _dilation_cells(res: float, step_xy: float, step_theta: float, reach: float) -> int:
    """Max-filter radius (cells) so a grid pose bounds every pose within half a step of it."""
    return int(np.ceil((0.5 * step_xy + 0.5 * step_theta * reach) / res))


def _grid_search(
    ref: ReferenceSubmap,
    query: np.ndarray,
    centre: np.ndarray,
    window_xy: float,
    window_theta: float,
    step_xy: float,
    step_theta: float,
    reach: float,
    max_lookups: int = 2_000_000,
) -> Steps[tuple[np.ndarray, np.ndarray]]:
    """Score every pose of a (thetas × offsets) grid: returns (P, 3) poses and (P,) scores.

    A generator (see :func:`match_scan_steps`): a step per chunk of headings scored with at most
    ``max_lookups`` field look-ups (at least one heading per chunk)."""
    res = ref.resolution
    h, w = ref.shape
    n_th = int(np.ceil(window_theta / step_theta))
    thetas = centre[2] + step_theta * np.arange(-n_th, n_th + 1)
    s = max(1, int(round(step_xy / res)))
    n_xy = int(np.ceil(window_xy / (s * res)))
    o = s * np.arange(-n_xy, n_xy + 1)
    ox, oy = (a.ravel() for a in np.meshgrid(o, o))
    cells = _dilation_cells(res, s * res, step_theta, reach)
    c, sn = np.cos(thetas)[:, None], np.sin(thetas)[:, None]
    px = c * query[None, :, 0] - sn * query[None, :, 1] + centre[0]
    py = sn * query[None, :, 0] + c * query[None, :, 1] + centre[1]
    bx = np.floor((px - ref.origin[0]) / res).astype(np.int64)
    by = np.floor((py - ref.origin[1]) / res).astype(np.int64)
    # points whose whole offset range would leave the grid see only the zero margin
    lim = n_xy * s
    out = (bx < lim) | (bx >= w - lim) | (by < lim) | (by >= h - lim)
    bx[out] = lim
    by[out] = lim
    # each point's window of offsets is a (n, n) block of the field with strides (s rows, s
    # columns) whose first cell is (bx - lim, by - lim): gathered as whole blocks of a strided
    # view (one index per point, not per point and offset), then laid out (t, O, M) as the
    # per-offset gather was, so that the means are the same sums in the same order
    n = 2 * n_xy + 1
    corner = (by - lim) * w + (bx - lim)  # (T, M), each block inside the grid (see `out`)
    scores = np.empty((len(thetas), n * n), np.float32)
    chunk = max(1, int(max_lookups // max(1, n * n * query.shape[0])))
    for a in range(0, len(thetas), chunk):
        cost = _MS_PER_LOOKUP * n * n * query.shape[0] * min(chunk, len(thetas) - a)
        yield cost + (_MS_PER_CELL_DILATE * h * w if cells not in ref._dilated else 0.0)
        field = ref.dilated(cells)
        step = field.strides[0]
        blocks = as_strided(
            field, shape=(field.size - 2 * lim * (w + 1), n, n), strides=(step, step * s * w, step * s)
        )
        at = corner[a : a + chunk]
        t, m = at.shape
        o_m = _scratch(0, (t, n * n, m), np.float32)  # (t, O, M), as np.ascontiguousarray
        # gathered a few headings at a time: a gather's result is a fresh array, from the heap
        # below _GATHER_BYTES, above a fresh mapping the kernel zero-fills page by page (the
        # pinned mmap threshold; FR079: 0.3 million page faults)
        sub = max(1, _GATHER_BYTES // (m * n * n * field.itemsize))
        for b in range(0, t, sub):
            g = blocks[at[b : b + sub]]  # (t', M, n, n): offset (oy, ox) at [.., iy, ix]
            np.copyto(o_m[b : b + sub], g.reshape(len(g), m, n * n).transpose(0, 2, 1))
        scores[a : a + chunk] = o_m.mean(axis=2)
    tt = np.repeat(thetas, n * n)
    poses = np.column_stack(
        (np.tile(centre[0] + ox * res, len(thetas)), np.tile(centre[1] + oy * res, len(thetas)), tt)
    )
    return poses, scores.ravel()


def _score_poses(ref: ReferenceSubmap, query: np.ndarray, poses: np.ndarray, cells: int) -> np.ndarray:
    """Mean (max-filtered) likelihood of ``query`` at each of ``poses`` (P, 3).

    Each (P, M) array is computed in place, with the same operations in the same order as
    ``floor((c qx - s qy + x - origin) / resolution)`` written out (the same cells)."""
    field = ref.dilated(cells)
    h, w = ref.shape
    pm = (len(poses), len(query))  # every (P, M) array in a scratch buffer (_scratch)
    c, s = np.cos(poses[:, 2])[:, None], np.sin(poses[:, 2])[:, None]
    qx, qy = query[None, :, 0], query[None, :, 1]
    px = np.multiply(c, qx, out=_scratch(0, pm, np.float64))
    tmp = np.multiply(s, qy, out=_scratch(1, pm, np.float64))
    px -= tmp
    px += poses[:, 0:1]
    py = np.multiply(s, qx, out=tmp)
    py += np.multiply(c, qy, out=_scratch(2, pm, np.float64))  # s qx + c qy: the same sum in either order
    py += poses[:, 1:2]
    for p, o in ((px, ref.origin[0]), (py, ref.origin[1])):
        p -= o
        p /= ref.resolution
        np.floor(p, out=p)
    bx, flat = _scratch(2, pm, np.int64), _scratch(3, pm, np.int64)
    np.copyto(bx, px, casting="unsafe")  # as astype(np.int64)
    np.copyto(flat, py, casting="unsafe")
    # outside the grid (negative indices too, seen as huge unsigned ones): the corner cell, in
    # the zero margin
    out = np.greater_equal(bx.view(np.uint64), w, out=_scratch(4, pm, np.bool_))
    out |= np.greater_equal(flat.view(np.uint64), h, out=_scratch(5, pm, np.bool_))
    flat *= w
    flat += bx
    flat[out] = 0
    # every index is in the grid: "clip" takes the same cells as "raise", without a buffer
    return np.take(field, flat, out=_scratch(0, pm, np.float32), mode="clip").mean(axis=1)


def _coarse_search(
    ref: ReferenceSubmap,
    query: np.ndarray,
    centre: np.ndarray,
    window_xy: float,
    window_theta: float,
    step_xy: float,
    step_theta: float,
    sep_xy: float = 1.0,
    sep_theta: float = np.deg2rad(10.0),
    max_lookups: int = 2_000_000,
) -> Steps[tuple[np.ndarray, np.ndarray]]:
    """Two-level correlative search: a grid at twice the steps on a wider max filter (an upper
    bound of the finer level), then the finer grid inside the best cells and the best distinct
    cells. Returns the finer-level (P, 3) poses and (P,) scores (a generator, see
    :func:`match_scan_steps`)."""
    reach = float(np.percentile(np.hypot(*query.T), 90)) if len(query) else 0.0
    poses1, scores1 = yield from _grid_search(
        ref, query, centre, window_xy, window_theta, 2.0 * step_xy, 2.0 * step_theta, reach, max_lookups
    )
    yield _MS_FINE + _MS_PER_CELL_DILATE * ref.shape[0] * ref.shape[1]
    n = min(len(scores1), 16)
    top = np.argpartition(-scores1, n - 1)[:n]
    cells = np.union1d(top, _distinct_peaks(poses1, scores1, 8, sep_xy, sep_theta))
    d = np.array([-1.0, 0.0, 1.0])
    dx, dy, dt = (a.ravel() for a in np.meshgrid(d * step_xy, d * step_xy, d * step_theta, indexing="ij"))
    fine = (poses1[cells][:, None, :] + np.column_stack((dx, dy, dt))[None]).reshape(-1, 3)
    res = ref.resolution
    s = max(1, int(round(step_xy / res)))
    scores = _score_poses(ref, query, fine, _dilation_cells(res, s * res, step_theta, reach))
    return fine, scores


def _distinct_peaks(
    poses: np.ndarray, scores: np.ndarray, k: int, sep_xy: float, sep_theta: float
) -> list[int]:
    """Indices of up to k best poses, pairwise at least (sep_xy or sep_theta) apart."""
    top = min(len(scores), 400)
    order = np.argpartition(-scores, top - 1)[:top]
    order = order[np.argsort(-scores[order])]
    cand = poses[order]
    alive = np.ones(len(order), bool)  # not within the separation of a picked peak
    picked: list[int] = []
    while len(picked) < k:
        left = np.flatnonzero(alive)
        if not len(left):
            break
        j = left[0]
        picked.append(int(order[j]))
        p = cand[j]
        near = (np.hypot(cand[:, 0] - p[0], cand[:, 1] - p[1]) < sep_xy) & (
            np.abs(_wrap(cand[:, 2] - p[2])) < sep_theta
        )
        alive &= ~near
    return picked


def icp_point_to_line(
    ref: ReferenceSubmap | LineMap,
    query: np.ndarray,
    pose: np.ndarray,
    iterations: int = 15,
    max_distance: float = 0.5,
    kernel: float = 0.05,
    sigma: float = 0.05,
) -> tuple[np.ndarray, np.ndarray] | None:
    """Point-to-line ICP of ``query`` onto the reference; returns (pose, 3×3 body covariance).
    From one start (the odometry's refinement); the matcher's peaks: :func:`icp_point_to_line_many`."""
    if len(ref.points) == 0 or len(query) < 10:
        return None
    x = np.asarray(pose, dtype=np.float64).copy()
    h = None
    near = None  # the reference's own way to its nearest points (ref.correspondences)
    qx, qy = np.ascontiguousarray(query[:, 0], np.float64), np.ascontiguousarray(query[:, 1], np.float64)
    for it in range(iterations):
        dmax = max_distance if it < iterations // 2 else max(2.0 * kernel, max_distance / 2.0)
        c, s = np.cos(x[2]), np.sin(x[2])  # transform_points(x, query), on contiguous columns
        moved = np.empty((len(query), 2))
        moved[:, 0] = x[0] + c * qx - s * qy
        moved[:, 1] = x[1] + s * qx + c * qy
        if near is None:
            near = ref.correspondences(moved, max_distance)
        sel, j, p, off = near.exact_nearest_offsets(moved, dmax)
        if len(sel) < 10:
            return None
        n, q = ref.line_normals(j)
        r = np.einsum("ij,ij->i", off, n)
        rel_x, rel_y = p[:, 0] - x[0], p[:, 1] - x[1]
        jac = np.empty((len(sel), 3))
        jac[:, 0], jac[:, 1] = n[:, 0], n[:, 1]
        jac[:, 2] = n[:, 1] * rel_x - n[:, 0] * rel_y
        wgt = q / (1.0 + (r / kernel) ** 2)
        h = jac.T @ (wgt[:, None] * jac)
        g = jac.T @ (wgt * r)
        try:
            delta = -np.linalg.solve(h + _EPS_EYE, g)
        except np.linalg.LinAlgError:
            return None
        x += delta
        x[2] = float(_wrap(x[2]))
        if np.hypot(delta[0], delta[1]) < 1e-4 and abs(delta[2]) < 1e-5:
            break
    if h is None:
        return None
    cov = _body_covariance(x, h, sigma)
    return None if cov is None else (x, cov)


def _body_covariance(x: np.ndarray, h: np.ndarray, sigma: float) -> np.ndarray | None:
    """3×3 body-frame covariance of an ICP pose ``x`` (x, y, theta) from its world-frame normal
    matrix ``h`` (point-to-line rows of unit weight ``sigma`` m); None when singular."""
    # world-frame (t, theta) -> body tangent (v, omega): t = t0 + R v
    c, s = np.cos(x[2]), np.sin(x[2])
    a = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    hb = a.T @ h @ a / sigma**2
    try:
        return np.linalg.inv(hb + 1e-9 * np.eye(3))
    except np.linalg.LinAlgError:
        return None


def icp_point_to_line_many(
    ref: ReferenceSubmap,
    query: np.ndarray,
    poses: np.ndarray,
    iterations: int = 15,
    max_distance: float = 0.5,
    kernel: float = 0.05,
    sigma: float = 0.05,
) -> Steps[list[tuple[np.ndarray, np.ndarray] | None]]:
    """:func:`icp_point_to_line` of ``query`` (M, 2) from each of ``poses`` (P, 3) in lockstep,
    each start's result bit for bit the one it gets alone: the same iterations, gates and
    arithmetic on its own rows (each element transformed by the same operations, its normal
    equations from its own contiguous rows by the same BLAS calls). Per iteration one k-d tree
    query for the points of every start still iterating and one pass of each array operation,
    instead of one per start: the matcher refines two or three peaks per candidate against the
    same reference (FR079: 2.9), and each numpy call and tree query has a fixed cost of
    microseconds to tens of them. A generator that yields (None) after each iteration but the
    last, so a caller can spread the iterations over its steps; its return value is the list
    of results (None where a start's ICP gave up, as :func:`icp_point_to_line` returns None)."""
    n_starts = len(poses)
    out: list[tuple[np.ndarray, np.ndarray] | None] = [None] * n_starts
    m = len(query)
    if len(ref.points) == 0 or m < 10 or iterations < 1:
        return out
    q = np.asarray(query, dtype=np.float64)
    qx, qy = np.ascontiguousarray(q[:, 0]), np.ascontiguousarray(q[:, 1])
    normals, quality = ref.normals, ref.quality
    x = np.array(poses, dtype=np.float64).reshape(n_starts, 3)
    h = np.zeros((n_starts, 3, 3))
    live = np.arange(n_starts)  # starts still iterating
    ended = np.zeros(n_starts, bool)  # converged or ran every iteration (the others gave up)
    for it in range(iterations):
        dmax = max_distance if it < iterations // 2 else max(2.0 * kernel, max_distance / 2.0)
        # each start's points as transform_points gives them (the same operations per element)
        xl = x[live]
        c, s = np.cos(xl[:, 2:3]), np.sin(xl[:, 2:3])
        moved = np.empty((len(live), m, 2))
        moved[:, :, 0] = xl[:, 0:1] + c * qx - s * qy
        moved[:, :, 1] = xl[:, 1:2] + s * qx + c * qy
        sel, j, p, off = ref.exact_nearest_offsets(moved.reshape(-1, 2), dmax)
        rows = np.searchsorted(sel, m * np.arange(len(live) + 1)).tolist()  # each start's rows
        n, w = normals[j], quality[j]
        r = np.einsum("ij,ij->i", off, n)
        own = np.repeat(np.arange(len(live)), np.diff(rows))
        rel_x, rel_y = p[:, 0] - xl[own, 0], p[:, 1] - xl[own, 1]
        jac = np.empty((len(sel), 3))
        jac[:, 0], jac[:, 1] = n[:, 0], n[:, 1]
        jac[:, 2] = n[:, 1] * rel_x - n[:, 0] * rel_y
        wgt = w / (1.0 + (r / kernel) ** 2)
        wj, wr = wgt[:, None] * jac, wgt * r
        kept, g = [], []
        for k in range(len(live)):
            a, b = rows[k], rows[k + 1]
            if b - a < 10:  # too few correspondences: that start gives up
                continue
            jt = jac[a:b].T
            h[live[k]] = jt @ wj[a:b]
            g.append(jt @ wr[a:b])
            kept.append(k)
        step = live[kept]
        if not len(step):
            live = step
            break
        gs = np.array(g)
        try:
            delta = -np.linalg.solve(h[step] + _EPS_EYE, gs[:, :, None])[:, :, 0]
        except np.linalg.LinAlgError:  # a singular start: each on its own (that one gives up)
            delta = np.zeros((len(step), 3))
            solved = np.ones(len(step), bool)
            for k, i in enumerate(step):
                try:
                    delta[k] = -np.linalg.solve(h[i] + _EPS_EYE, gs[k])
                except np.linalg.LinAlgError:
                    solved[k] = False
            step, delta = step[solved], delta[solved]
        x[step] += delta
        x[step, 2] = _wrap(x[step, 2])
        converged = (np.hypot(delta[:, 0], delta[:, 1]) < 1e-4) & (np.abs(delta[:, 2]) < 1e-5)
        ended[step[converged]] = True
        live = step[~converged]
        if not len(live) or it + 1 == iterations:
            break
        yield None
    ended[live] = True
    for i in np.flatnonzero(ended):
        cov = _body_covariance(x[i], h[i], sigma)
        if cov is not None:
            out[i] = (x[i].copy(), cov)
    return out


def _advance(steps: Steps[T], n: int | None) -> T | None:
    """Run up to ``n`` more steps of ``steps`` (None: all the rest); its result if it ended
    meanwhile, else None."""
    while n is None or n > 0:
        try:
            next(steps)
        except StopIteration as stop:
            return stop.value
        n = None if n is None else n - 1
    return None


def match_scan(
    reference: ReferenceSubmap,
    query: np.ndarray,
    centre: np.ndarray,
    window_xy: float,
    window_theta: float,
    config: LoopClosureConfig | None = None,
    rng: np.random.Generator | None = None,
) -> ScanMatch | None:
    """Match ``query`` points (M, 2, query frame) against ``reference`` around ``centre``
    (x, y, theta of the query frame in the reference frame) within ± window_xy (m) and
    ± window_theta (rad). None when nothing can be matched (too few points / no overlap)."""
    return run_steps(match_scan_steps(reference, query, centre, window_xy, window_theta, config, rng))


def match_scan_steps(
    reference: ReferenceSubmap,
    query: np.ndarray,
    centre: np.ndarray,
    window_xy: float,
    window_theta: float,
    config: LoopClosureConfig | None = None,
    rng: np.random.Generator | None = None,
) -> Steps[ScanMatch | None]:
    """:func:`match_scan` as a generator that yields between bounded pieces of work (a chunk of
    the correlative search of at most ``MAX_LOOKUPS_PER_STEP`` look-ups, the finer level,
    building the reference's ICP data, one ICP refinement); its return value is the match.
    The anytime loop closer runs a few pieces per scan; the result does not depend on how the
    pieces are spread."""
    cfg = config or LoopClosureConfig()
    q = np.asarray(query, dtype=np.float64).reshape(-1, 2)
    q = q[np.hypot(*q.T) <= cfg.max_point_range] if len(q) else q
    fine = voxel_downsample(q, 2.0 * cfg.resolution)
    if len(fine) < 20 or len(reference.points) < 20:
        return None
    coarse = fine
    if len(coarse) > MAX_QUERY_POINTS:
        rng = rng or np.random.default_rng(0)
        coarse = coarse[rng.choice(len(coarse), MAX_QUERY_POINTS, replace=False)]
    step_th = np.deg2rad(COARSE_STEP_THETA_DEG)
    c0 = np.asarray(centre, dtype=np.float64)
    sep_xy, sep_th = PEAK_SEPARATION_XY, np.deg2rad(PEAK_SEPARATION_THETA_DEG)
    poses, scores = yield from _coarse_search(
        reference,
        coarse,
        c0,
        window_xy,
        min(window_theta, np.pi),
        COARSE_STEP_XY,
        step_th,
        sep_xy,
        sep_th,
        MAX_LOOKUPS_PER_STEP,
    )
    peaks = _distinct_peaks(poses, scores, 3, sep_xy, sep_th)
    top = float(scores[peaks[0]])
    if top < MIN_COARSE_SCORE:  # not even the optimistic coarse score: no ICP
        second = float(scores[peaks[1]]) / top if len(peaks) > 1 and top > 0 else 0.0
        return ScanMatch(poses[peaks[0]], 0.0, second, np.eye(3), top, len(fine), None)
    cells = reference.shape[0] * reference.shape[1]
    if reference._nearest is None:
        yield _MS_PER_CELL_NEAREST * cells
        reference.nearest  # noqa: B018
    if reference._normals is None:
        yield _MS_PER_POINT_NORMALS * len(reference.points)
        reference.prepare_icp()
    refined, unrefined, refine = [], 0.0, []
    for j in peaks:
        if j != peaks[0] and scores[j] < REFINE_RATIO * top:
            unrefined = max(unrefined, float(scores[j]) / top)  # clearly lower already
        else:
            refine.append(j)
    # the peaks in lockstep (icp_point_to_line_many), its iterations spread over one step per
    # peak, each announcing one peak's ICP as before (the same schedule)
    icp = icp_point_to_line_many(
        reference,
        fine,
        poses[refine],
        ICP_ITERATIONS,
        ICP_MAX_DISTANCE,
        kernel=INLIER_DISTANCE / 2.0,
        sigma=ICP_SIGMA,
    )
    results = None
    for k in range(len(refine)):
        yield _MS_ICP + _MS_PER_POINT_ICP * len(fine) * ICP_ITERATIONS
        if results is None:  # this step's share of the iterations (the last step: all the rest)
            share = (k + 1) * ICP_ITERATIONS // len(refine) - k * ICP_ITERATIONS // len(refine)
            results = _advance(icp, share if k + 1 < len(refine) else None)
    assert results is not None  # the last step ran the rest
    for j, r in zip(refine, results, strict=True):
        if r is None:
            continue
        inl = reference.inlier_fraction(fine, r[0], INLIER_DISTANCE)
        refined.append((inl, r[0], r[1], float(scores[j])))
    if not refined:
        return None
    if not reference._free_costed and reference._scans:
        # the free-space mask's step in the cost model; the mask itself is built below, only
        # for a match the closer could accept (the schedule stays the one the model was fitted with)
        yield _MS_PER_CELL_FREE * cells
        reference._free_costed = True
    refined.sort(key=lambda t: -t[0])
    best = refined[0]
    second, second_pose = 0.0, None
    for inl, p, _, _ in refined[1:]:
        if np.hypot(*(p[:2] - best[1][:2])) >= sep_xy or abs(_wrap(p[2] - best[1][2])) >= sep_th:
            second, second_pose = inl, p
            break
    amb = max(second / best[0], unrefined) if best[0] > 0 else 1.0
    # refused anyway (too few inliers, even to confirm a pending closure, or ambiguous): the
    # free-space test is not needed (NaN); most candidates end here (FR079: 7 in 10)
    refused = (
        best[0] < min(cfg.min_inlier_fraction, cfg.confirm_min_inlier_fraction) or amb > cfg.max_ambiguity
    )
    free = math.nan if refused else reference.free_violation(fine, best[1])
    return ScanMatch(best[1], best[0], float(amb), best[2], top, len(fine), second_pose, free)


__all__ = [
    "LineMap",
    "ReferenceSubmap",
    "ScanMatch",
    "first_of_each",
    "icp_point_to_line",
    "icp_point_to_line_many",
    "match_scan",
    "match_scan_steps",
    "point_bounds",
    "rigid_points",
    "stable_order",
    "transform_points",
    "voxel_downsample",
]
