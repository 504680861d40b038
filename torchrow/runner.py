"""Run either implementation over many inputs, in input order, never aborting on one bad input.

``impl="reference"`` calls :func:`torchrow.reference.detect` image by image;
``impl="tensor"`` batches images of the same working size through
:class:`torchrow.detector.CropRowDetector`. Both yield ``(index, working rgb or None, result,
seconds)`` in input order (``seconds``: detection time of the image; for a batch, its wall
time divided by its size); an input that cannot be loaded, or a failure inside detection,
yields an ``error`` result and the run goes on.
"""

from __future__ import annotations

import time
from typing import Callable, Iterator, Sequence

import numpy as np

from .io import ImageError
from .params import Params
from .results import ImageResult

__all__ = ["IMPLS", "run"]

IMPLS = ("tensor", "reference", "onnx")

Loader = Callable[[], np.ndarray]


def _progress(total: int, desc: str, enabled: bool):
    from .progress import progress

    return progress(total, desc, enabled, unit="image")


def _load(name: str, loader: Loader) -> tuple[np.ndarray | None, ImageResult | None]:
    try:
        return loader(), None
    except (ImageError, OSError) as exc:
        return None, ImageResult.failed(name, str(exc))


def run(items: Sequence[tuple[str, Loader]], impl: str = "tensor", params: Params | None = None,
        batch_size: int = 64, device: str | None = None, progress: bool = True,
        desc: str = "detect", model: str | None = None) -> Iterator[tuple[int, np.ndarray | None, ImageResult, float]]:
    """Detect every ``(name, loader)`` item; ``loader()`` returns the working RGB image.

    Results come back in input order. With ``impl="tensor"`` up to ``batch_size`` images per
    working size are held in memory until their batch runs. ``impl="onnx"`` runs the exported
    model ``model`` (:mod:`torchrow.export`) in onnxruntime, in batches of the model's static
    batch size (the last one padded; ``batch_size`` is ignored) with the model's parameters;
    images of another working size than the model's get an ``error`` record.
    """
    params = params or Params()
    if impl not in IMPLS:
        raise ValueError(f"impl must be one of {IMPLS}, got {impl!r}")
    if impl == "onnx":
        if model is None:
            raise ValueError("impl='onnx' needs model= (an ONNX file written by torchrow.export.to_onnx)")
        from .export import OnnxDetector

        det = OnnxDetector(model)
        batch_size = det.batch
    bar = _progress(len(items), desc, progress)
    try:
        if impl == "reference":
            from .reference import detect

            for i, (name, loader) in enumerate(items):
                rgb, err = _load(name, loader)
                t0 = time.perf_counter()
                if err is None:
                    try:
                        err = detect(rgb, params, name=name)
                    except Exception as exc:  # a detector failure is a record, not a crash
                        err = ImageResult.failed(name, f"{type(exc).__name__}: {exc}", rgb.shape[1], rgb.shape[0])
                bar.update(1)
                yield i, rgb, err, time.perf_counter() - t0
            return
        yield from _run_tensor(items, params, batch_size, device, bar, det if impl == "onnx" else None)
    finally:
        bar.close()


def _run_tensor(items, params, batch_size, device, bar, det=None):
    import torch

    from .detector import CropRowDetector

    if det is None:
        det = CropRowDetector(params, device=device)
    done: dict[int, tuple[np.ndarray | None, ImageResult, float]] = {}
    groups: dict[tuple[int, ...], list[int]] = {}
    rgbs: dict[int, np.ndarray] = {}
    next_out = 0

    def flush(key):
        idx = groups.pop(key)
        batch = torch.from_numpy(np.stack([rgbs[i] for i in idx])).permute(0, 3, 1, 2).contiguous()
        t0 = time.perf_counter()
        try:
            results = det(batch).results([items[i][0] for i in idx])
        except Exception as exc:  # keep the run alive; every image of the batch gets the error
            results = [ImageResult.failed(items[i][0], f"{type(exc).__name__}: {exc}") for i in idx]
        dt = (time.perf_counter() - t0) / len(idx)
        for i, res in zip(idx, results):
            done[i] = (rgbs.pop(i), res, dt)
        bar.update(len(idx))

    for i, (name, loader) in enumerate(items):
        rgb, err = _load(name, loader)
        if err is not None:
            done[i] = (None, err, 0.0)
            bar.update(1)
        else:
            rgbs[i] = rgb
            groups.setdefault(rgb.shape, []).append(i)
            if len(groups[rgb.shape]) >= batch_size:
                flush(rgb.shape)
        while next_out in done:
            yield (next_out, *done.pop(next_out))
            next_out += 1
    for key in list(groups):
        flush(key)
    while next_out in done:
        yield (next_out, *done.pop(next_out))
        next_out += 1
