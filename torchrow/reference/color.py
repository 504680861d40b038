"""Reference vegetation colour by greedy LAB clustering (ALGORITHM.md section 2)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from torchrow.core.params import Params
from torchrow.core.tables import pack_rgb, rgb_to_lab

__all__ = ["ColorCluster", "distinct_colors", "cluster_colors", "vegetation_color", "LIME"]

LIME = (0, 255, 0)


@dataclass(frozen=True)
class ColorCluster:
    """A colour cluster: its seed colour (RGB) and the total pixel count it absorbed."""

    seed: tuple[int, int, int]
    count: int


def distinct_colors(rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distinct colours of ``(H, W, 3)`` uint8 RGB, ordered by count (descending), ties by
    first appearance in raster order.

    Returns ``colors (n, 3)`` uint8 and ``counts (n,)`` int64.
    """
    codes = pack_rgb(rgb.reshape(-1, 3))
    uniq, first, counts = np.unique(codes, return_index=True, return_counts=True)
    order = np.lexsort((first, -counts))  # last key is primary
    uniq, counts = uniq[order], counts[order]
    colors = np.stack([(uniq >> 16) & 255, (uniq >> 8) & 255, uniq & 255], axis=1).astype(np.uint8)
    return colors, counts.astype(np.int64)


def cluster_colors(colors: np.ndarray, counts: np.ndarray, params: Params) -> list[ColorCluster]:
    """Greedy clustering (section 2) of colours already in walk order.

    Walking the order, a colour not yet absorbed becomes a seed and absorbs every later,
    not yet absorbed colour whose CIE76 distance ``sqrt((dL^2 + da^2) + db^2)`` to it is
    ``< color_tol``. Returns the clusters sorted by total count (descending, stable), all
    of them (the caller keeps the first ``n_colors``).
    """
    lab = rgb_to_lab(colors)
    remaining = np.arange(len(colors))
    clusters: list[ColorCluster] = []
    while remaining.size:
        seed, rest = remaining[0], remaining[1:]
        d = lab[rest] - lab[seed]
        dist = np.sqrt((d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1]) + d[:, 2] * d[:, 2])
        near = dist < params.color_tol
        total = int(counts[seed]) + int(counts[rest[near]].sum())
        clusters.append(ColorCluster(tuple(int(c) for c in colors[seed]), total))  # type: ignore[arg-type]
        remaining = rest[~near]
    order = sorted(range(len(clusters)), key=lambda i: -clusters[i].count)  # stable
    return [clusters[i] for i in order]


def vegetation_color(rgb: np.ndarray, params: Params) -> tuple[tuple[int, int, int], list[ColorCluster]]:
    """Section 2: the vegetation colour of a ``(H, W, 3)`` uint8 RGB image.

    The seed RGB of the kept cluster (first ``n_colors`` by count) closest to lime
    ``(0, 255, 0)`` in RGB (ties: first). Returns ``(colour, kept clusters)``.
    """
    colors, counts = distinct_colors(rgb)
    kept = cluster_colors(colors, counts, params)[: params.n_colors]
    best, best_d = kept[0], None
    for cl in kept:
        d = sum((int(a) - int(b)) ** 2 for a, b in zip(cl.seed, LIME))
        if best_d is None or d < best_d:
            best, best_d = cl, d
    return best.seed, kept
