"""Place recognition for loop-closure candidates: a rotation-invariant polar descriptor of a
keyframe's submap (points in metres in the keyframe's frame; angles in radians).

A polar occupancy grid as Scan Context (Kim & Kim, IROS 2018) in 2-D: ``RINGS`` rings of
``DESCRIPTOR_RANGE / RINGS`` metres by ``SECTORS`` sectors around the keyframe, a bin is 1 where
any point falls (binary: the density of a scan falls with range and with the beam count; the
layout of walls does not), then blurred by a Gaussian of one bin (wrapping round the sectors).
Points nearer than ``DESCRIPTOR_MIN_RANGE`` are left out: their bearing swings most when the two
keyframes stand a little apart. On the single loop of ``tools/dev_big_loop.py`` (a keyframe's
scan against those of the first lap, the query 0.4 m off a first-lap pose and turned at random,
50 queries) the place within 0.9 m ranked first for 58 % of the queries and among the first three
for 66 %; without the blur and with all points, 28 % and 42 % (Scan Context is known to be
sensitive to translation; the blur and the near cut halve that). Two descriptors are compared over every circular shift of the sectors
(the unknown relative heading): the similarity at a shift is the sum of the cosines of the
matching sector columns over the number of non-empty columns of the fuller descriptor (Scan
Context's distance), computed for all shifts at once by an FFT along the sectors. The best shift
is the relative heading of the two keyframes (to a sector). The distance does not depend on the
poses the graph estimates, only on what the scans saw: :class:`~frslam_graph.loop_closure.closer.LoopCloser`
ranks the candidates within a wide search radius by it (the best-looking places are matched
first) where the estimate no longer says where the robot is.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable, Sequence

import numpy as np
from scipy.ndimage import gaussian_filter

# Fixed settings (config fields until issue 20; never changed by a test, tool or doc):
DESCRIPTOR_RANGE = 12.0  # m; points farther from the keyframe are left out of its descriptor
DESCRIPTOR_MIN_RANGE = 2.0  # m; ... and points nearer than this
RINGS = 20  # radial bins (0.6 m each)
SECTORS = 60  # angular bins (6 deg each); the heading resolution of the comparison


def polar_descriptor(points: np.ndarray, max_range: float = DESCRIPTOR_RANGE) -> np.ndarray:
    """Blurred binary polar occupancy (RINGS, SECTORS; float32) of ``points`` (N, 2; m, the
    keyframe's frame, origin at the keyframe): :func:`blurred` of :func:`polar_occupancy`."""
    return blurred(polar_occupancy(points, max_range))


def blurred(occupancy: np.ndarray) -> np.ndarray:
    """Occupancies (..., RINGS, SECTORS) blurred by a Gaussian of one bin along the rings and the
    sectors (wrapping round), each descriptor on its own (float32)."""
    occ = np.asarray(occupancy, dtype=np.float32)
    sigma = (0.0,) * (occ.ndim - 2) + (1.0, 1.0)
    return gaussian_filter(occ, sigma, mode=("nearest",) * (occ.ndim - 1) + ("wrap",))


def polar_occupancy(points: np.ndarray, max_range: float = DESCRIPTOR_RANGE) -> np.ndarray:
    """Binary polar occupancy (RINGS, SECTORS; bool) of ``points`` (N, 2; m, the keyframe's frame,
    origin at the keyframe). Sector k spans headings [-pi + k·2pi/SECTORS, ...), ring j ranges
    [j, j + 1) · max_range / RINGS. Points nearer than ``DESCRIPTOR_MIN_RANGE``, at or beyond
    ``max_range`` and non-finite points are ignored; no points give all False."""
    out = np.zeros((RINGS, SECTORS), bool)
    p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    p = p[np.isfinite(p).all(axis=1)]
    if not len(p):
        return out
    r = np.hypot(p[:, 0], p[:, 1])
    ok = (r >= DESCRIPTOR_MIN_RANGE) & (r < max_range)
    ring = (r[ok] * (RINGS / max_range)).astype(np.int64)
    a = np.arctan2(p[ok, 1], p[ok, 0])
    sector = np.minimum(((a + np.pi) * (SECTORS / (2.0 * np.pi))).astype(np.int64), SECTORS - 1)
    out[ring, sector] = True
    return out


def descriptor_spectra(descriptors: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """What :func:`spectrum_distances` compares, per descriptor (K, RINGS, SECTORS): the FFT
    along the sectors of its sector columns scaled to unit length (K, RINGS, SECTORS // 2 + 1;
    complex) and its number of non-empty columns (K,). Each descriptor on its own (the same values
    in any batch), so a keyframe's spectrum can be kept and compared with every later query."""
    d = np.asarray(descriptors, dtype=np.float64).reshape(-1, RINGS, SECTORS)
    norm = np.sqrt(np.sum(d * d, axis=-2, keepdims=True))
    unit = d / np.where(norm > 0.0, norm, 1.0)
    return np.fft.rfft(unit, axis=-1), np.count_nonzero(norm[..., 0, :], axis=-1)


def spectrum_distances(
    query: tuple[np.ndarray, np.ndarray], candidates: tuple[np.ndarray, np.ndarray]
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`descriptor_distances` from :func:`descriptor_spectra`: ``query`` (spectrum (RINGS,
    F) or (1, RINGS, F), non-empty columns), ``candidates`` (spectra (K, RINGS, F), columns (K,))."""
    q_spec, q_cols = np.asarray(query[0]).reshape(RINGS, -1), int(np.asarray(query[1]).reshape(-1)[0])
    c_spec, c_cols = candidates
    k = len(c_spec)
    if not k:
        return np.zeros(0), np.zeros(0)
    # corr[k, s] = sum_j q_j . c_{k, j+s}: cross-correlation along the sectors, summed over rings
    spec = np.sum(np.conj(q_spec)[None] * c_spec, axis=1)
    corr = np.fft.irfft(spec, n=SECTORS, axis=-1)
    shift = np.argmax(corr, axis=1)
    cols = np.maximum(np.maximum(q_cols, c_cols), 1)
    sim = np.where((q_cols > 0) & (c_cols > 0), corr[np.arange(k), shift] / cols, 0.0)
    heading = np.where(shift > SECTORS // 2, shift - SECTORS, shift) * (2.0 * np.pi / SECTORS)
    return np.clip(1.0 - sim, 0.0, 1.0), heading


def descriptor_distances(query: np.ndarray, candidates: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Scan Context distance in [0, 1] (0: the same place) of ``query`` (RINGS, SECTORS) to each
    of ``candidates`` (K, RINGS, SECTORS) at the best sector shift, and that shift as the relative
    heading (rad, K) of the query in the candidate's frame. An empty descriptor is at distance 1
    from everything (heading 0). The similarity at a shift is the sum of the cosines of the
    matching sector columns over the number of non-empty columns of the fuller descriptor, all
    shifts at once by an FFT along the sectors (:func:`descriptor_spectra`)."""
    return spectrum_distances(descriptor_spectra(query), descriptor_spectra(candidates))


# candidates per spectrum_distances call of SpectrumCache.distances (its arrays ~160 kB: from the
# heap, under the pinned mmap threshold offline.MMAP_THRESHOLD)
_DISTANCE_ROWS = 16


class SpectrumCache:
    """The :func:`descriptor_spectra` of at most ``capacity`` keyframes (the least recently used
    dropped first; ~10 kB each), computed from their packed occupancies: each keyframe's when its
    descriptor is made (:meth:`keep`), a dropped one's again when it is compared. A ranked plan
    compares the query with every keyframe within its radius, most of them the previous plan's
    too: transforming them all anew each time (blur, unit columns, FFT: ~30 us a keyframe) made a
    keyframe scan of FR079 take up to 32 ms for the ranking alone at 1,100 keyframes. The values
    are the same as computed anew (each descriptor on its own)."""

    def __init__(self, capacity: int) -> None:
        self.capacity = int(capacity)
        self._slot: OrderedDict[int, int] = OrderedDict()  # keyframe -> row of the arrays below
        self._spec = np.zeros((0, RINGS, SECTORS // 2 + 1), np.complex128)
        self._cols = np.zeros(0, np.int64)
        self.computed = 0  # descriptors transformed so far

    def __len__(self) -> int:
        return len(self._slot)

    def clear(self) -> None:
        self._slot.clear()

    def keep(self, keys: Sequence[int], packed: Callable[[int], np.ndarray]) -> None:
        """Compute and keep the spectra of those of keyframes ``keys`` not kept (the last
        ``capacity`` of them); ``packed(k)`` gives keyframe k's occupancy as packed bits
        (``np.packbits`` of :func:`polar_occupancy`)."""
        miss = [k for k in dict.fromkeys(int(k) for k in keys) if k not in self._slot][-self.capacity :]
        if not miss:
            return
        spec, cols = _spectra_of(np.stack([packed(k) for k in miss]))
        self.computed += len(miss)
        if len(self._spec) < self.capacity:  # the rows at once (pages are touched as they fill)
            grown = np.empty((self.capacity, *spec.shape[1:]), spec.dtype)
            grown[: len(self._spec)] = self._spec
            self._spec, self._cols = grown, np.resize(self._cols, self.capacity)
        rows = []
        for k in miss:
            row = self._slot.popitem(last=False)[1] if len(self._slot) >= self.capacity else len(self._slot)
            self._slot[k] = row
            rows.append(row)
        self._spec[rows], self._cols[rows] = spec, cols

    def spectra(
        self, keys: Sequence[int], packed: Callable[[int], np.ndarray]
    ) -> tuple[np.ndarray, np.ndarray]:
        """Spectra (K, RINGS, F) and non-empty columns (K,) of keyframes ``keys`` (``packed``: as
        :meth:`keep`)."""
        spec, cols, rows = self._rows(keys, packed)
        return (spec, cols) if rows is None else (spec[rows], cols[rows])

    def distances(self, keys: Sequence[int], packed: Callable[[int], np.ndarray]) -> np.ndarray:
        """:func:`spectrum_distances` of keyframe ``keys[0]`` to each of ``keys[1:]`` (K - 1,),
        ``_DISTANCE_ROWS`` candidates at a time: the same numbers as on :meth:`spectra`'s arrays,
        without their (K, RINGS, F) copies and products (10 kB per keyframe: arrays of 0.3-4 MB
        were fresh mappings whose pages the kernel zero-filled)."""
        spec, cols, rows = self._rows(keys, packed)
        at = np.arange(len(keys)) if rows is None else np.asarray(rows)
        query = (spec[at[0]], cols[at[0]])
        parts = [
            spectrum_distances(query, (spec[at[a : a + _DISTANCE_ROWS]], cols[at[a : a + _DISTANCE_ROWS]]))[0]
            for a in range(1, len(at), _DISTANCE_ROWS)
        ]
        return np.concatenate(parts) if parts else np.zeros(0)

    def _rows(
        self, keys: Sequence[int], packed: Callable[[int], np.ndarray]
    ) -> tuple[np.ndarray, np.ndarray, list[int] | None]:
        """(spectra, columns, rows of ``keys`` in them): the cache's arrays, or the spectra of
        ``keys`` computed anew (rows None) when more than can be kept at once."""
        keys = [int(k) for k in keys]
        if len(set(keys)) > self.capacity:  # more than can be kept at once: all anew
            self.computed += len(keys)
            spec, cols = _spectra_of(np.stack([packed(k) for k in keys]))
            return spec, cols, None
        for k in keys:  # the ones kept first, so that keeping the others drops none of them
            if k in self._slot:
                self._slot.move_to_end(k)
        self.keep(keys, packed)
        return self._spec, self._cols, [self._slot[k] for k in keys]


def _spectra_of(packed: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`descriptor_spectra` of the blurred occupancies given as packed bits (K, bytes)."""
    occ = np.unpackbits(packed, axis=1, count=RINGS * SECTORS).reshape(-1, RINGS, SECTORS)
    return descriptor_spectra(blurred(occ))


__all__ = [
    "DESCRIPTOR_MIN_RANGE",
    "DESCRIPTOR_RANGE",
    "RINGS",
    "SECTORS",
    "SpectrumCache",
    "blurred",
    "descriptor_distances",
    "descriptor_spectra",
    "polar_descriptor",
    "polar_occupancy",
    "spectrum_distances",
]
