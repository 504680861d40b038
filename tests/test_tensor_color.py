"""Batched vegetation colour (torchrow.functional.color) against the reference, exactly."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from torchrow.core.params import Params
from torchrow.core.tables import rgb_to_lab
from torchrow.functional import color as fc
from torchrow.reference import color as rc

P = Params()


# --------------------------------------------------------------------------- helpers
def to_batch(images: list[np.ndarray]) -> torch.Tensor:
    """List of (H, W, 3) uint8 -> uint8 (B, 3, H, W)."""
    return torch.from_numpy(np.stack(images)).permute(0, 3, 1, 2).contiguous()


def to_hwc(t: torch.Tensor) -> np.ndarray:
    return np.ascontiguousarray(t.permute(1, 2, 0).numpy())


def pack(rgb: np.ndarray) -> np.ndarray:
    rgb = np.asarray(rgb, dtype=np.int64)
    return (rgb[..., 0] << 16) | (rgb[..., 1] << 8) | rgb[..., 2]


def lab_dist(c1, c2) -> float:
    """The reference's CIE76 distance, written as in reference/color.py."""
    lab = rgb_to_lab(np.array([c1, c2], dtype=np.uint8))
    d = lab[1] - lab[0]
    return float(np.sqrt((d[0] * d[0] + d[1] * d[1]) + d[2] * d[2]))


def check_image_equal(batch: torch.Tensor, params: Params = P, pipeline: bool = True, **kw) -> None:
    """Every stage, every image of ``batch``, equal to the reference. ``pipeline``: also
    run :func:`vegetation_clusters` (with ``kw``) and require the same kept clusters."""
    dc = fc.distinct_colors(batch)
    clusters = fc.cluster_colors(*fc.trim_colors(dc), params)
    srt = fc.sort_clusters(clusters)
    kept = fc.kept_clusters(clusters, params)
    if pipeline:
        for a, b in zip(fc.vegetation_clusters(batch, params, **kw), kept):
            assert torch.equal(a, b)
    for i in range(batch.shape[0]):
        img = to_hwc(batch[i])
        colors, counts = rc.distinct_colors(img)
        n = len(colors)
        assert int(dc.valid[i].sum()) == n
        assert bool(dc.valid[i, :n].all()) and not bool(dc.valid[i, n:].any())
        np.testing.assert_array_equal(dc.codes[i, :n].numpy(), pack(colors))
        np.testing.assert_array_equal(dc.counts[i, :n].numpy(), counts)
        ref = rc.cluster_colors(colors, counts, params)
        k = len(ref)
        assert int(srt.valid[i].sum()) == k
        assert int(clusters.valid[i].sum()) == k
        np.testing.assert_array_equal(srt.seeds[i, :k].numpy(), pack([c.seed for c in ref]))
        np.testing.assert_array_equal(srt.totals[i, :k].numpy(), [c.count for c in ref])
        assert int(srt.totals[i, :k].sum()) == img.shape[0] * img.shape[1]
        col, kept_ref = rc.vegetation_color(img, params)
        assert tuple(kept.color[i].tolist()) == col
        m = len(kept_ref)
        assert kept.valid[i].tolist() == [True] * m + [False] * (params.n_colors - m)
        assert [tuple(s) for s in kept.seeds[i, :m].tolist()] == [c.seed for c in kept_ref]
        assert kept.counts[i, :m].tolist() == [c.count for c in kept_ref]
        assert tuple(kept.seeds[i, int(kept.chosen[i])].tolist()) == col


def find_pair(base=(90, 140, 60), axis=1, tol=P.color_tol):
    """Offsets along one RGB axis: the largest k with distance < tol and the next one."""
    below = None
    for k in range(1, 60):
        c = list(base)
        c[axis] += k
        if lab_dist(base, c) < tol:
            below = k
        else:
            return below, k
    raise AssertionError("no boundary found")


def shifted(base, axis, k):
    c = list(base)
    c[axis] += k
    return tuple(c)


# --------------------------------------------------------------------------- CRBD
@pytest.fixture(scope="module")
def crbd_batch(crbd_dir: Path) -> torch.Tensor:
    from torchrow.core.io import load_image

    files = sorted(p for p in (crbd_dir / "Images").iterdir() if p.suffix.lower() == ".jpg")
    assert files
    return to_batch([load_image(p, 320) for p in files[::3]])


@pytest.mark.data
def test_crbd_every_third_image_equals_reference(crbd_batch: torch.Tensor) -> None:
    for i in range(0, crbd_batch.shape[0], 24):  # the stage ops in batches of up to 24
        check_image_equal(crbd_batch[i:i + 24], pipeline=False)


@pytest.mark.data
def test_crbd_batch_composition_and_chunking(crbd_batch: torch.Tensor) -> None:
    sub = crbd_batch[:6]
    ref = fc.vegetation_clusters(sub, P, chunk_pixels=None)
    perm = torch.tensor([4, 1, 5, 0, 3, 2])
    for out, order in ((fc.vegetation_clusters(sub[perm], P, chunk_pixels=None), perm),
                       (fc.vegetation_clusters(sub, P, chunk_pixels=2 * 320 * 240), torch.arange(6))):
        for a, b in zip(out, ref):
            assert torch.equal(a, b[order])
    alone = fc.vegetation_clusters(sub[3:4], P)
    for a, b in zip(alone, ref):
        assert torch.equal(a, b[3:4])


# --------------------------------------------------------------------------- synthetic
def test_ties_in_counts_and_first_appearance() -> None:
    # 4x4 image: colours with equal counts appear in a known raster order.
    A, B, C, D, E = (10, 20, 30), (200, 10, 10), (10, 200, 10), (10, 10, 200), (0, 255, 0)
    img = np.array([[C, A, B, D],
                    [A, C, B, D],
                    [E, E, E, B],
                    [A, C, D, E]], dtype=np.uint8)
    # counts: A 3, C 3, B 3, D 3, E 4 -> walk: E, then C, A, B, D (first appearance)
    dc = fc.distinct_colors(to_batch([img]))
    n = int(dc.valid.sum())
    assert n == 5
    assert dc.codes[0, :n].tolist() == pack([E, C, A, B, D]).tolist()
    assert dc.counts[0, :n].tolist() == [4, 3, 3, 3, 3]
    check_image_equal(to_batch([img]))
    # totals tie too: stable sort keeps seed order
    kept = fc.vegetation_clusters(to_batch([img]), P)
    assert [tuple(s) for s in kept.seeds[0, :5].tolist()] == [E, C, A, B, D]
    assert tuple(kept.color[0].tolist()) == E


def test_lime_distance_tie_picks_first() -> None:
    # (0,225,0) and (30,255,0) are both at squared distance 900 from lime, 13.9 apart in
    # LAB. Counts 3 and 2 order them; the first kept wins the tie.
    X, Y, Z = (0, 225, 0), (30, 255, 0), (120, 40, 200)
    img = np.array([[Y, X, X], [X, Y, Z]], dtype=np.uint8)
    assert lab_dist(X, Y) >= P.color_tol
    kept = fc.vegetation_clusters(to_batch([img]), P)
    assert tuple(kept.color[0].tolist()) == X and int(kept.chosen[0]) == 0
    check_image_equal(to_batch([img]))


def test_single_colour_and_one_pixel() -> None:
    one = np.full((7, 5, 3), (12, 34, 56), dtype=np.uint8)
    kept = fc.vegetation_clusters(to_batch([one]), P)
    assert tuple(kept.color[0].tolist()) == (12, 34, 56)
    assert kept.counts[0].tolist() == [35] + [0] * (P.n_colors - 1)
    assert kept.valid[0].tolist() == [True] + [False] * (P.n_colors - 1)
    check_image_equal(to_batch([one]))
    px = np.array([[[255, 0, 255]]], dtype=np.uint8)
    dc = fc.distinct_colors(to_batch([px]))
    assert dc.codes.tolist() == [[0xFF00FF]] and dc.counts.tolist() == [[1]] and dc.valid.tolist() == [[True]]
    check_image_equal(to_batch([px, np.zeros_like(px)]))


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_two_colours_at_the_tolerance_boundary(axis: int) -> None:
    base = (90, 140, 60)
    below, above = find_pair(base, axis)
    near, far = shifted(base, axis, below), shifted(base, axis, above)
    assert lab_dist(base, near) < P.color_tol <= lab_dist(base, far)
    imgs = []
    for other in (near, far):
        img = np.empty((3, 4, 3), dtype=np.uint8)
        img[:] = base
        img[2, 1:] = other
        imgs.append(img)
    kept = fc.vegetation_clusters(to_batch(imgs), P)
    assert kept.counts[0, :2].tolist() == [12, 0]  # absorbed: one cluster
    assert kept.counts[1, :2].tolist() == [9, 3]  # not absorbed: two clusters
    check_image_equal(to_batch(imgs))


def test_distance_exactly_equal_to_tolerance() -> None:
    """color_tol set to a pair's exact float64 distance: strict < must not absorb; the next
    float up must; both paths agree."""
    base, other = (90, 140, 60), (90, 146, 60)
    d = lab_dist(base, other)
    img = np.empty((2, 3, 3), dtype=np.uint8)
    img[:] = base
    img[1, 2] = other
    for tol, n_clusters in ((d, 2), (math.nextafter(d, math.inf), 1), (math.nextafter(d, 0.0), 2)):
        params = P.replace(color_tol=tol)
        kept = fc.vegetation_clusters(to_batch([img]), params)
        assert int(kept.valid[0].sum()) == n_clusters, tol
        check_image_equal(to_batch([img]), params)


def test_greedy_chain_order_matters() -> None:
    """A absorbs B, C (close to B, far from A) stays its own seed: greedy, not transitive."""
    base = (90, 140, 60)
    below, _ = find_pair(base, 1)
    A, B, C = base, shifted(base, 1, below), shifted(base, 1, 2 * below)
    assert lab_dist(A, B) < P.color_tol and lab_dist(B, C) < P.color_tol <= lab_dist(A, C)
    img = np.array([[A, A, A], [B, B, C]], dtype=np.uint8)
    kept = fc.vegetation_clusters(to_batch([img]), P)
    assert [tuple(s) for s in kept.seeds[0, :2].tolist()] == [A, C]
    assert kept.counts[0, :2].tolist() == [5, 1]
    # B more frequent than A: B seeds and takes both A and C.
    img2 = np.array([[B, B, B], [A, A, C]], dtype=np.uint8)
    kept2 = fc.vegetation_clusters(to_batch([img2]), P)
    assert kept2.counts[0, :2].tolist() == [6, 0]
    check_image_equal(to_batch([img, img2]))


def test_smallest_tolerance_every_colour_its_own_cluster() -> None:
    """color_tol at its lower bound (1, Params): colours 60 apart never merge."""
    rng = np.random.default_rng(3)
    img = rng.integers(0, 4, (6, 6, 3), dtype=np.uint8) * 60
    params = P.replace(color_tol=1.0, n_colors=100)
    dc = fc.distinct_colors(to_batch([img]))
    cl = fc.cluster_colors(*dc, params)
    n = int(dc.valid.sum())
    assert int(cl.valid.sum()) == n
    assert torch.equal(cl.totals[0, :n], dc.counts[0, :n])
    check_image_equal(to_batch([img]), params)


palettes = st.lists(st.tuples(st.integers(0, 255), st.integers(0, 255), st.integers(0, 255)),
                    min_size=1, max_size=6)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data(), h=st.integers(1, 6), w=st.integers(1, 7), b=st.integers(1, 4),
       jitter=st.integers(0, 6))
def test_random_small_batches_equal_reference(data, h: int, w: int, b: int, jitter: int) -> None:
    """Small palettes (many ties in counts), jittered to land near the tolerance."""
    imgs = []
    for _ in range(b):
        pal = np.array(data.draw(palettes), dtype=np.int64)
        idx = np.array(data.draw(st.lists(st.integers(0, len(pal) - 1), min_size=h * w, max_size=h * w)))
        j = np.array(data.draw(st.lists(st.integers(-jitter, jitter), min_size=3, max_size=3)))
        img = pal[idx].reshape(h, w, 3)
        img[h // 2:] += j  # a second, nearby family of colours
        imgs.append(np.clip(img, 0, 255).astype(np.uint8))
    check_image_equal(to_batch(imgs), chunk_pixels=None)
    check_image_equal(to_batch(imgs), chunk_pixels=1)


def test_noise_image_many_clusters_and_static_mode() -> None:
    """Random noise: almost every colour its own cluster; early_exit=False agrees."""
    rng = np.random.default_rng(0)
    imgs = [rng.integers(0, 256, (5, 6, 3), dtype=np.uint8) for _ in range(2)]
    imgs.append(np.full((5, 6, 3), 7, dtype=np.uint8))
    batch = to_batch(imgs)
    check_image_equal(batch)
    a = fc.vegetation_clusters(batch, P, early_exit=True)
    b = fc.vegetation_clusters(batch, P, early_exit=False)
    for x, y in zip(a, b):
        assert torch.equal(x, y)
    dc = fc.distinct_colors(batch)
    s1 = fc.sort_clusters(fc.cluster_colors(*dc, P, early_exit=False))
    s2 = fc.sort_clusters(fc.cluster_colors(*fc.trim_colors(dc), P, early_exit=True))
    k = s2.seeds.shape[1]
    assert s1.seeds.shape[1] == dc.codes.shape[1]  # static width N
    assert torch.equal(s1.seeds[:, :k], s2.seeds) and torch.equal(s1.totals[:, :k], s2.totals)
    assert not bool(s1.valid[:, k:].any())


def test_mixed_batch_independent_of_composition() -> None:
    rng = np.random.default_rng(5)
    base = (90, 140, 60)
    imgs = [
        rng.integers(0, 256, (8, 9, 3), dtype=np.uint8),  # noise
        np.full((8, 9, 3), 200, dtype=np.uint8),  # one colour
        np.clip(np.array(base) + rng.integers(-8, 9, (8, 9, 3)), 0, 255).astype(np.uint8),  # one family
        (rng.integers(0, 3, (8, 9, 3)) * 100).astype(np.uint8),  # few colours, ties
    ]
    batch = to_batch(imgs)
    check_image_equal(batch)
    full = fc.vegetation_clusters(batch, P, chunk_pixels=None)
    for i in range(4):
        alone = fc.vegetation_clusters(batch[i:i + 1], P)
        for a, b in zip(alone, full):
            assert torch.equal(a, b[i:i + 1])
    perm = torch.tensor([2, 0, 3, 1, 2])  # shuffled, with a duplicate
    shuf = fc.vegetation_clusters(batch[perm], P, chunk_pixels=None)
    for a, b in zip(shuf, full):
        assert torch.equal(a, b[perm])
    assert torch.equal(fc.vegetation_color(batch, P), full.color)
    assert torch.equal(fc.VegetationColor(P)(batch), full.color)
    mod = fc.VegetationColor(P)(batch, return_clusters=True)
    assert torch.equal(mod.counts, full.counts)


def test_large_batch_and_int64_key_paths(monkeypatch: pytest.MonkeyPatch) -> None:
    """More than 127 images (int64 first-sort keys) and the forced all-int64 key path."""
    rng = np.random.default_rng(11)
    imgs = [(rng.integers(0, 3, (2, 3, 3)) * 120).astype(np.uint8) for _ in range(130)]
    batch = to_batch(imgs)
    check_image_equal(batch, chunk_pixels=None)
    ref = fc.distinct_colors(batch[:5])
    monkeypatch.setattr(fc, "_INT32_KEYS", False)
    for a, b in zip(fc.distinct_colors(batch[:5]), ref):
        assert torch.equal(a, b)


@settings(deadline=None, max_examples=40, suppress_health_check=[HealthCheck.too_slow])
@given(st.integers(1, 6), st.integers(1, 9), st.integers(1, 9), st.integers(1, 256), st.integers(0, 2**31 - 1))
def test_distinct_colors_sync_and_static_paths_agree(b: int, h: int, w: int, levels: int, seed: int) -> None:
    """The compacted second sort (``sync=True``, default) equals the static all-pixel one."""
    rng = np.random.default_rng(seed)
    batch = torch.from_numpy(rng.integers(0, levels, (b, 3, h, w), dtype=np.int64).astype(np.uint8))
    for a, c in zip(fc.distinct_colors(batch, sync=True), fc.distinct_colors(batch, sync=False)):
        assert torch.equal(a, c)


def test_non_contiguous_input() -> None:
    rng = np.random.default_rng(9)
    hwc = torch.from_numpy(rng.integers(0, 5, (3, 6, 7, 3), dtype=np.uint8) * 50)
    view = hwc.permute(0, 3, 1, 2)  # not contiguous
    assert not view.is_contiguous()
    a = fc.vegetation_clusters(view, P)
    b = fc.vegetation_clusters(view.contiguous(), P)
    for x, y in zip(a, b):
        assert torch.equal(x, y)


def test_empty_batch() -> None:
    empty = torch.zeros((0, 3, 4, 5), dtype=torch.uint8)
    dc = fc.distinct_colors(empty)
    assert dc.codes.shape == (0, 20) and dc.counts.shape == (0, 20) and dc.valid.shape == (0, 20)
    assert fc.trim_colors(dc).codes.shape == (0, 0)
    cl = fc.cluster_colors(*dc, P)
    assert cl.seeds.shape[0] == 0
    out = fc.vegetation_clusters(empty, P)
    assert out.color.shape == (0, 3) and out.color.dtype == torch.uint8
    assert out.seeds.shape == (0, P.n_colors, 3) and out.counts.shape == (0, P.n_colors)
    assert fc.vegetation_color(empty, P, chunk_pixels=None).shape == (0, 3)
    assert fc.VegetationColor(P)(empty).shape == (0, 3)


def test_output_types() -> None:
    batch = torch.zeros((2, 3, 2, 2), dtype=torch.uint8)
    dc = fc.distinct_colors(batch)
    assert (dc.codes.dtype, dc.counts.dtype, dc.valid.dtype) == (torch.int64, torch.int64, torch.bool)
    assert dc.codes[0].tolist() == [0, -1, -1, -1] and dc.counts[0].tolist() == [4, 0, 0, 0]
    out = fc.vegetation_clusters(batch, P)
    assert out.color.dtype == torch.uint8 and out.seeds.dtype == torch.uint8
    assert out.counts.dtype == torch.int64 and out.valid.dtype == torch.bool and out.chosen.dtype == torch.int64
    assert fc.unpack_codes(torch.tensor([0x123456, -1])).tolist() == [[0x12, 0x34, 0x56], [0, 0, 0]]


def test_bad_inputs() -> None:
    good = torch.zeros((1, 3, 2, 2), dtype=torch.uint8)
    for bad in (good.float(), good.to(torch.int16), good[0], good[:, :2], torch.zeros((1, 4, 2, 2), dtype=torch.uint8),
                torch.zeros((1, 3, 0, 2), dtype=torch.uint8)):
        with pytest.raises(ValueError):
            fc.distinct_colors(bad)
        with pytest.raises(ValueError):
            fc.vegetation_color(bad, P)
    with pytest.raises(TypeError):
        fc.vegetation_color(np.zeros((1, 3, 2, 2), np.uint8), P)  # type: ignore[arg-type]
    with pytest.raises(ValueError):
        fc.vegetation_color(good, P, chunk_pixels=0)
    dc = fc.distinct_colors(good)
    with pytest.raises(ValueError):
        fc.cluster_colors(dc.codes, dc.counts[:, :2], dc.valid, P)
    with pytest.raises(ValueError):
        fc.cluster_colors(dc.codes.int(), dc.counts, dc.valid, P)
    with pytest.raises(ValueError):
        fc.cluster_colors(dc.codes, dc.counts, dc.valid.long(), P)
    with pytest.raises(ValueError):
        fc.cluster_colors(dc.codes[0], dc.counts[0], dc.valid[0], P)
    with pytest.raises(ValueError):
        fc.cluster_colors(torch.full_like(dc.codes, 1 << 24), dc.counts, dc.valid, P)
    with pytest.raises(TypeError):
        fc.cluster_colors(dc.codes.numpy(), dc.counts, dc.valid, P)  # type: ignore[arg-type]


@pytest.mark.parametrize("tol", [0.0, 1e-300, 0.5, 1.0, 2.0, 6.0, 7.3, 10.0, 1e150, 1e200])
def test_squared_threshold_equivalent_to_sqrt(tol: float) -> None:
    """sqrt(s) < tol  <=>  s < T, on the floats around tol**2 and around T."""
    t = fc._sq_threshold(tol)
    centres = {t, tol * tol} if math.isfinite(tol * tol) else {t}
    for c in centres:
        if not math.isfinite(c):
            continue
        s = c
        for _ in range(40):
            s = math.nextafter(s, 0.0)
        for _ in range(80):
            assert (math.sqrt(s) < tol) == (s < t), (tol, s, t)
            assert bool(np.sqrt(np.float64(s)) < tol) == (s < t)
            s = math.nextafter(s, math.inf)
    # (torch.sqrt is deliberately not used: on the CPU build here it is not correctly
    # rounded, e.g. torch.sqrt(nextafter(0.25, 0)) == 0.5 while IEEE/numpy give 0.5 - 2**-54.)
