"""The loop closer's reference submaps: large arrays kept on the inner grid only, and the arrays
of dropped submaps reused by the next ones (:class:`GridPool`) instead of fresh mappings whose
pages the kernel zero-fills (session 22): the same numbers either way."""

from __future__ import annotations

import numpy as np

from frslam_graph.loop_closure import closer as closer_module
from frslam_graph.loop_closure import submap_matching as sm
from frslam_graph.loop_closure.closer import LoopCloser


def _room(rng: np.random.Generator, scale: float) -> np.ndarray:
    """Noisy walls of a 12 m × 9 m room (times ``scale``) with a pillar (m), moved a little."""
    t = np.linspace(0.0, 1.0, 800)
    walls = [
        np.column_stack((12.0 * t, 0.0 * t)),
        np.column_stack((12.0 * t, 0.0 * t + 9.0)),
        np.column_stack((0.0 * t, 9.0 * t)),
        np.column_stack((0.0 * t + 12.0, 9.0 * t)),
        np.column_stack((4.0 + 2.0 * t, 0.0 * t + 4.0)),
    ]
    return scale * np.concatenate(walls) + rng.uniform(-1.0, 1.0, 2) + rng.normal(0.0, 0.01, (4000, 2))


def _build(pts: np.ndarray, pool: sm.GridPool | None) -> tuple[sm.ReferenceSubmap, sm.ScanMatch]:
    """A submap as the closer builds it (5 cm, 5.9 m margin, free-space mask) and a match on it."""
    ref = sm.ReferenceSubmap(pts, 0.05, 0.1, 5.9, [(pts.mean(axis=0), pts)], pool=pool)
    query = sm.transform_points(np.array([0.1, -0.05, 0.03]), pts[::9])
    match = sm.match_scan(ref, query, np.zeros(3), 2.0, np.deg2rad(10.0))
    assert match is not None and ref._nearest is not None and len(ref._dilated) == 2
    return ref, match


def _same(a: tuple[sm.ReferenceSubmap, sm.ScanMatch], b: tuple[sm.ReferenceSubmap, sm.ScanMatch]) -> None:
    (ra, ma), (rb, mb) = a, b
    assert np.array_equal(ma.pose, mb.pose) and np.array_equal(ma.covariance, mb.covariance)
    assert (ma.inlier_fraction, ma.ambiguity, ma.coarse_score) == (
        mb.inlier_fraction,
        mb.ambiguity,
        mb.coarse_score,
    )
    assert np.array_equal(ra.field, rb.field) and np.array_equal(ra.nearest, rb.nearest)
    assert np.array_equal(ra.free, rb.free)
    assert sorted(ra._dilated) == sorted(rb._dilated)
    for c in ra._dilated:
        assert np.array_equal(ra._dilated[c], rb._dilated[c])


def test_a_submap_keeps_its_grids_on_the_inner_grid():
    """The likelihood field and the nearest-point map cover the inner grid only (the margin's
    values are implied): ~40 % fewer cells than the whole grid for a room at the closer's margin."""
    rng = np.random.default_rng(1)
    ref, _ = _build(_room(rng, 1.0), None)
    pad, hi_, wi = ref._inner
    h, w = ref.shape
    assert pad > 0 and ref.field.shape == (hi_, wi) and ref.nearest.shape == (hi_ * wi,)
    assert ref.field.size < 0.6 * h * w
    # laid on the whole grid, the margin holds what it stands for
    assert np.count_nonzero(ref.padded(ref.field, 0.0)) == np.count_nonzero(ref.field)
    assert np.count_nonzero(ref.padded(ref.nearest, -1) >= 0) == np.count_nonzero(ref.nearest >= 0)


def _span(a: np.ndarray) -> tuple[int, int]:
    """The bytes of its block an array covers (a view's whole block)."""
    b = a if a.base is None else a.base
    start = b.__array_interface__["data"][0]
    return start, start + b.nbytes


def test_a_dropped_submaps_arrays_serve_the_next_submap_with_the_same_numbers():
    rng = np.random.default_rng(2)
    pool = sm.GridPool()
    held = [_build(_room(rng, 1.0), pool)[0]]
    # where its arrays lie (addresses: a reference to one would keep it from the pool)
    spans = [_span(a) for a in (held[0].field, held[0].nearest, *held[0]._dilated.values())]
    assert len(pool._blocks) == 1  # the labels, once the nearest-point map is built from them
    spans.append(_span(pool._blocks[0]))
    held.pop().release()  # the closer drops it: field, nearest-point map, two max-filtered fields
    assert len(pool._blocks) == 5
    pts = _room(rng, 0.97)  # a slightly smaller room: every array fits a block
    pooled = _build(pts, pool)
    assert pool.reused == 5 and len(pool._blocks) == 1  # the new labels, once used
    ref = pooled[0]
    for a in (ref.field, ref.nearest, *ref._dilated.values()):  # no fresh mapping
        lo, hi = _span(a)
        assert any(s0 <= lo and hi <= s1 for s0, s1 in spans)
    _same(pooled, _build(pts, None))  # the numbers of a submap built afresh


def test_a_submap_still_referenced_keeps_its_arrays():
    """A submap dropped from the cache while a suspended match holds it (or a view of one of
    its arrays) gives nothing to the pool that is still in use."""
    rng = np.random.default_rng(3)
    pool = sm.GridPool()
    ref, _ = _build(_room(rng, 1.0), pool)
    assert len(pool._blocks) == 1  # the labels, once the nearest-point map is built from them
    ref.release()  # `ref` still held here
    assert len(pool._blocks) == 1 and ref._nearest is not None
    view = next(iter(ref._dilated.values()))[10:]  # a look-up's view of a max-filtered field
    held = [ref]
    del ref
    held.pop().release()
    assert len(pool._blocks) == 4  # labels, field, nearest-point map: not the viewed max filter
    assert not any(np.shares_memory(view, b) for b in pool._blocks)


def test_the_pool_gives_a_block_only_to_a_request_near_its_size():
    pool = sm.GridPool(capacity=2)
    pool.put(np.zeros(1 << 20, np.uint8))
    assert pool.take((100, 100), np.float32) is None  # 40 kB: the block would hold 1 MB for it
    a = pool.take((500, 500), np.float32)  # 1,000,000 bytes in 1,048,576
    assert a is not None and a.shape == (500, 500) and a.dtype == np.float32 and a.flags.c_contiguous
    for _ in range(3):
        pool.put(np.zeros(1 << 20, np.uint8))
    assert len(pool._blocks) == 2  # capacity: the oldest freed


def test_the_closer_hands_dropped_submaps_to_its_pool_before_a_build():
    """LoopCloser._make_room drops the least recently used submap (or a stale one) before the
    next build, so that build's arrays come from it."""
    released = []

    class Sub:
        def release(self) -> None:
            released.append(self)

    lc = LoopCloser()
    kept = closer_module.SUBMAPS_KEPT
    for c in range(kept):
        lc._make_room()
        lc._keep_submap(c, Sub())
    assert not released
    first = lc._submaps[0]
    lc._make_room()  # the next build's room
    assert released == [first] and len(lc._submaps) == kept - 1
    assert isinstance(lc._pool, sm.GridPool)


def test_place_distances_in_chunks_are_those_of_the_whole_arrays():
    """SpectrumCache.distances compares a query with its candidates 16 at a time (no (K, RINGS,
    F) copies and products of 0.3-4 MB): the same numbers as spectrum_distances on spectra()."""
    from frslam_graph.loop_closure import place

    rng = np.random.default_rng(4)
    bits = place.RINGS * place.SECTORS
    packed = {k: np.packbits(rng.random(bits) < rng.uniform(0.02, 0.4)) for k in range(300)}
    packed[5] = np.packbits(np.zeros(bits, np.uint8))  # an empty descriptor
    for capacity, k in ((400, 1), (400, 17), (400, 250), (100, 250)):  # 100: computed anew
        keys = [5, *(int(x) for x in rng.choice(np.arange(6, 300), k, replace=False))]
        whole, chunked = place.SpectrumCache(capacity), place.SpectrumCache(capacity)
        spec, cols = whole.spectra(keys, packed.__getitem__)
        expected = place.spectrum_distances((spec[0], cols[0]), (spec[1:], cols[1:]))[0]
        assert np.array_equal(chunked.distances(keys, packed.__getitem__), expected)
