"""Run either implementation over many inputs, in input order, never aborting on one bad input.

``impl="reference"`` calls :func:`torchrow.reference.detect` image by image;
``impl="tensor"`` batches images of the same working size through
:class:`torchrow.engines.detector.CropRowDetector`. Both yield ``(index, working rgb or None, result,
seconds)`` in input order (``seconds``: detection time of the image; for a batch, its wall
time divided by its size); an input that cannot be loaded, or a failure inside detection,
yields an ``error`` result and the run goes on. A loader may return
:class:`torchrow.core.io.Evidenced` (the image and the caller's row evidence at its size,
ALGORITHM.md 11.1.1) instead of the image: that image is detected with its evidence (improved
mode; batches never mix images with and without evidence).

Ordering window (``impl="tensor"``/``"onnx"``): images wait in per-working-size groups until
a group holds ``batch_size`` images; finished results wait until every earlier input's result
is out. So that one image of an odd size (or a rare size) cannot hold the output back, at most
``window`` inputs (default :func:`default_window`, ``2 * batch_size``; with ``workers``
concurrent onnxruntime runs, ``(workers + 1) * batch_size`` if that is more) are read ahead of the
oldest input without a result: when the window is full, the group holding that input runs at
once, even if it is not full. Memory is bounded by ``window`` working images (about 230 kB
each at 320x240), whatever the length of the run. Discrete outputs never depend on the window
(or on ``batch_size``), since images are independent of the batch they run in; floats may
differ in their last bits where a sum runs over a batch's padded sizes (seen: 2.2e-16), within
the 1e-6 of ALGORITHM.md "Identical results".
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from torchrow.core.camera import CameraModel
from torchrow.core.io import Evidenced, ImageError
from torchrow.core.params import Params
from torchrow.core.progress import progress as progress_bar
from torchrow.core.results import ImageResult
from torchrow.core.steering import FrameResult

if TYPE_CHECKING:  # the run imports them when it needs them (import time of the CLI)
    from torchrow.engines.detector import CropRowDetector
    from torchrow.onnx.runtime import OnnxDetector

__all__ = ["IMPLS", "run", "default_window", "onnx_model", "onnx_workers", "track", "track_batches", "source_size",
           "native_size", "load_camera"]

IMPLS = ("tensor", "reference", "onnx")

Loader = Callable[[], "np.ndarray | Evidenced"]


def _load(name: str, loader: Loader) -> np.ndarray | Evidenced | ImageResult:
    """The working RGB image (with its evidence where the loader gives it), or the ``error``
    result of an input that cannot be loaded."""
    try:
        return loader()
    except (ImageError, OSError) as exc:
        return ImageResult.failed(name, str(exc))


def default_window(batch_size: int) -> int:
    """Default ordering window: ``2 * batch_size`` inputs (module docstring)."""
    return 2 * batch_size


def run(items: Iterable[tuple[str, Loader]], impl: str = "tensor", params: Params | None = None,
        batch_size: int = 64, device: str | None = None, progress: bool = True,
        desc: str = "detect", model: str | None = None, window: int | None = None,
        total: int | None = None, detector: CropRowDetector | OnnxDetector | None = None,
        workers: int | None = None
        ) -> Iterator[tuple[int, np.ndarray | None, ImageResult, float]]:
    """Detect every ``(name, loader)`` item; ``loader()`` returns the working RGB image, or
    :class:`~torchrow.core.io.Evidenced` (the image and its row evidence, improved mode; an
    ``error`` record with ``impl="onnx"`` or in faithful mode).

    ``items`` may be a lazy iterable (read one item at a time; ``total`` sizes the progress
    bar when it has no ``len``). Results come back in input order, each as soon as every
    earlier input's result is out; ``window`` bounds the images held (module docstring). ``impl="onnx"`` runs the exported
    model ``model`` (:mod:`torchrow.onnx`) in onnxruntime, in batches of the model's static
    batch size (the last one padded; ``batch_size`` is ignored) with the model's parameters;
    images of another working size than the model's get an ``error`` record. ``detector``: an
    already built :class:`~torchrow.engines.detector.CropRowDetector` (or ``OnnxDetector``) to use
    instead of a new one (the Ray engine's workers keep one each).

    ``workers`` (``impl="onnx"`` only): batches run concurrently on this many threads, each
    onnxruntime run on one intra-op thread (default :func:`onnx_workers` when the run opens
    the model, 1 with a given ``detector``). onnxruntime gets little from a second intra-op
    thread on this graph of small operations (a run waits on thread hand-offs between them),
    while images are independent: two one-thread runs side by side use both cores. Results
    and their order do not depend on it.
    """
    params = params or Params()
    if impl not in IMPLS:
        raise ValueError(f"impl must be one of {IMPLS}, got {impl!r}")
    if total is None and hasattr(items, "__len__"):
        total = len(items)  # type: ignore[arg-type]
    det: CropRowDetector | OnnxDetector | None
    if impl == "onnx":
        model = onnx_model(model)
        from torchrow.onnx.runtime import OnnxDetector

        if workers is None:
            workers = 1 if detector is not None else onnx_workers()
        if workers < 1:
            raise ValueError(f"workers must be >= 1, got {workers}")
        if detector is None:
            det = OnnxDetector(model, threads=1 if workers > 1 else None)
        elif isinstance(detector, OnnxDetector):
            det = detector
        else:
            raise TypeError(f"impl='onnx' runs an OnnxDetector, got {type(detector).__name__}")
        batch_size = det.batch
    else:
        if workers not in (None, 1):
            raise ValueError(f"workers is only used with impl='onnx', got {workers} for impl={impl!r}")
        det = detector
        workers = 1
    if window is None:  # room for every worker's batch and the next one being gathered
        window = max(default_window(batch_size), (workers + 1) * batch_size)
    if window < batch_size:
        raise ValueError(f"window must be >= batch_size ({batch_size}), got {window}")
    bar = progress_bar(total, desc, progress, unit="image")
    try:
        if impl == "reference":
            from torchrow.reference import detect

            for i, (name, loader) in enumerate(items):
                got = _load(name, loader)
                t0 = time.perf_counter()
                rgb: np.ndarray | None = None
                if isinstance(got, ImageResult):
                    res = got
                else:
                    rgb, ev = got if isinstance(got, Evidenced) else (got, None)
                    try:
                        res = detect(rgb, params, name=name, evidence=ev)
                    except Exception as exc:  # a detector failure is a record, not a crash
                        res = ImageResult.failed(name, f"{type(exc).__name__}: {exc}", rgb.shape[1], rgb.shape[0])
                bar.update(1)
                yield i, rgb, res, time.perf_counter() - t0
            return
        yield from _run_tensor(items, params, batch_size, window, device, bar, det, workers)
    finally:
        bar.close()


def onnx_model(model: str | None) -> str:
    """``model`` of an ``impl="onnx"`` run, or the error saying that it is missing."""
    if model is None:
        raise ValueError("impl='onnx' needs model= (an ONNX file written by torchrow.onnx.export.to_onnx)")
    return model


def onnx_workers() -> int:
    """Default concurrent onnxruntime runs of :func:`run`: the cores this process may use, at most 4
    (each run holds its own intermediate tensors, about 0.1 GB at 320x240)."""
    import os

    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    return max(1, min(cores, 4))


def _run_tensor(items: Iterable[tuple[str, Loader]], params: Params, batch_size: int, window: int, device: str | None,
                bar: Any, det: CropRowDetector | OnnxDetector | None = None, workers: int = 1
                ) -> Iterator[tuple[int, np.ndarray | None, ImageResult, float]]:
    from collections import deque
    from concurrent.futures import ThreadPoolExecutor

    import torch

    from torchrow.engines.detector import CropRowDetector

    if det is None:
        det = CropRowDetector(params, device=device)
    done: dict[int, tuple[np.ndarray | None, ImageResult, float]] = {}
    # a group: images of one working (H, W, 3) that all have, or all lack, row evidence
    groups: dict[tuple[tuple[int, ...], bool], list[int]] = {}
    rgbs: dict[int, np.ndarray] = {}
    evs: dict[int, np.ndarray] = {}
    names: dict[int, str] = {}
    next_out = 0
    pool = None
    if workers > 1:
        from torchrow.core.tables import lab_table_torch

        lab_table_torch("cpu")  # the shared colour table exists before the workers read it
        # one torch thread per worker (OpenMP's setting is per thread): the workers' host-side
        # colour clustering must not spin up a second pool on the cores the other runs use
        pool = ThreadPoolExecutor(workers, thread_name_prefix="torchrow-onnx",
                                  initializer=torch.set_num_threads, initargs=(1,))
    pending: deque = deque()  # (indices, future) of batches on the pool, in submission order

    def detect(batch, evidence, idx, key):
        t0 = time.perf_counter()
        try:
            if evidence is None:
                out = det(batch)
            elif isinstance(det, CropRowDetector):
                out = det(batch, evidence=evidence)
            else:
                raise ValueError("row evidence (ALGORITHM.md 11.1.1) is read by impl 'tensor' and 'reference'; "
                                 "the ONNX detector takes images only")
            results = out.results([names[i] for i in idx])
        except Exception as exc:  # keep the run alive; every image of the batch gets the error
            h, w = key[0][:2]
            results = [ImageResult.failed(names[i], f"{type(exc).__name__}: {exc}", w, h) for i in idx]
        return results, (time.perf_counter() - t0) / len(idx)

    def store(idx, results, dt):
        for i, res in zip(idx, results):
            done[i] = (rgbs.pop(i), res, dt)
        bar.update(len(idx))

    def collect(wait: bool = False):
        """Store finished batches in submission order; ``wait``: the oldest one at least."""
        while pending and (wait or pending[0][1].done()):
            idx, fut = pending.popleft()
            store(idx, *fut.result())
            wait = False

    def flush(key):
        idx = groups.pop(key)
        batch = torch.from_numpy(np.stack([rgbs[i] for i in idx])).permute(0, 3, 1, 2).contiguous()
        evidence = torch.from_numpy(np.stack([evs.pop(i) for i in idx])) if key[1] else None
        if pool is None:
            store(idx, *detect(batch, evidence, idx, key))
            return
        while len(pending) >= workers:
            collect(wait=True)
        pending.append((idx, pool.submit(detect, batch, evidence, idx, key)))
        collect()

    def group_of(i):
        return rgbs[i].shape, i in evs

    def ready():
        nonlocal next_out
        while next_out in done:
            yield (next_out, *done.pop(next_out))
            names.pop(next_out)
            next_out += 1

    n = 0
    try:
        for i, (name, loader) in enumerate(items):
            n = i + 1
            names[i] = name
            got = _load(name, loader)
            if isinstance(got, ImageResult):
                done[i] = (None, got, 0.0)
                bar.update(1)
            else:
                if isinstance(got, Evidenced):
                    rgb, evs[i] = got
                else:
                    rgb = got
                rgbs[i] = rgb
                key = group_of(i)
                groups.setdefault(key, []).append(i)
                if len(groups[key]) >= batch_size:
                    flush(key)
            collect()
            yield from ready()
            while n - next_out >= window:  # the window is full: the oldest waiting input's result first
                if any(next_out in idx for idx, _ in pending):
                    collect(wait=True)
                else:
                    flush(group_of(next_out))
                yield from ready()
        for key in sorted(groups, key=lambda k: groups[k][0]):
            flush(key)
            yield from ready()
        while pending:
            collect(wait=True)
            yield from ready()
    finally:
        if pool is not None:
            pool.shutdown(wait=True, cancel_futures=True)
    assert next_out == n and not done


def source_size(src, params: Params) -> tuple[int, int] | None:
    """A sequence's working ``(H, W)``: :meth:`torchrow.core.frames.FrameSource.working_size` (the
    size most of its frames have) where the source has one, else that of its first readable
    frame; ``None`` if no frame is readable."""
    from torchrow.core.frames import load_item

    if hasattr(src, "working_size"):
        return src.working_size(params.video_width, params.max_pixels)
    for item in src:
        got = load_item(item, params.video_width, params.max_pixels)
        if got.rgb is not None:
            return got.rgb.shape[:2]
    return None


def native_size(src) -> tuple[int, int] | None:
    """``(W0, H0)`` of a sequence's first readable frame as stored, before any resizing (one
    frame is decoded); ``None`` if no frame is readable."""
    for item in src:
        frame = item[1] if isinstance(item, tuple) and len(item) == 2 else item
        try:
            rgb = frame() if callable(frame) else frame
        except (ImageError, OSError):
            continue
        if isinstance(rgb, np.ndarray) and rgb.ndim >= 2:
            return (int(rgb.shape[1]), int(rgb.shape[0]))
    return None


def load_camera(path: str | Path, sources: Sequence) -> CameraModel:
    """The camera model of ``path`` (:meth:`CameraModel.from_json`) for the sources' frames.

    Its pixels are those of the stored frames, so every source must store frames of one size
    (that of its first readable frame). Raises ``ValueError`` with a one-line reason.
    """
    sizes = {getattr(s, "name", str(i)): native_size(s) for i, s in enumerate(sources)}
    known = {k: v for k, v in sizes.items() if v is not None}
    if not known:
        raise ValueError(f"camera model {path}: no source has a readable frame to take its size from")
    if len(set(known.values())) > 1:
        (a, sa), (b, sb) = (min(known.items(), key=lambda kv: kv[1]), max(known.items(), key=lambda kv: kv[1]))
        raise ValueError(f"camera model {path} describes frames of one size; {a} has {sa[0]}x{sa[1]}, "
                         f"{b} has {sb[0]}x{sb[1]}")
    return CameraModel.from_json(path, next(iter(known.values())))


def track(sources: Sequence, names: Sequence[str], impl: str = "tensor", params: Params | None = None,
          batch_size: int = 8, device: str | None = None, hfov_deg: float | None = None,
          workers: int | None = None, onnx=None, camera: CameraModel | None = None
          ) -> Iterator[tuple[int, FrameResult, np.ndarray | None]]:
    """Track frame sources (:func:`torchrow.core.frames.open_source`); yields ``(source index,
    FrameResult, working RGB or None)``.

    ``impl="reference"`` tracks the sources one after the other; ``"tensor"`` in batches of
    up to ``batch_size`` sources of one working size (lock-step order within a batch).
    Frames that carry a ``stamp_ns`` (ROS bag messages) pass it to their result. Results
    stream as the trackers make them. ``workers``: :class:`~torchrow.engines.tracker.Tracker`'s
    (default: torch's thread count on a CPU). ``impl="onnx"`` runs ``onnx``, an
    :class:`~torchrow.onnx.runtime.OnnxTracker`, on batches of its model's batch size (its own
    ``camera``). ``camera``: the trackers' (:class:`~torchrow.engines.tracker.Tracker`).
    """
    params = params or Params()
    stamps: dict[tuple[int, int], int] = {}

    def tapped(b: int):
        for j, item in enumerate(sources[b]):
            st = getattr(item[1], "stamp_ns", None) if isinstance(item, tuple) else None
            if st is not None:
                stamps[(b, j)] = st
            yield item

    def stamped(b: int, res: FrameResult) -> FrameResult:
        res.stamp_ns = stamps.pop((b, res.frame), None)
        return res

    if impl == "reference":
        from torchrow.reference import Tracker as RefTracker

        ref = RefTracker(params, hfov_deg=hfov_deg, camera=camera)
        for b in range(len(sources)):
            for res, rgb in ref.track_iter(tapped(b), names[b], source_size(sources[b], params)):
                yield b, stamped(b, res), rgb
        return
    if impl == "onnx":
        if onnx is None:
            raise ValueError("impl='onnx' needs onnx=OnnxTracker(model)")
        for batch in track_batches(sources, impl, params, batch_size, onnx=onnx):
            for k, res, rgb in onnx.track_iter([tapped(b) for b in batch], [names[b] for b in batch]):
                yield batch[k], stamped(batch[k], res), rgb
        return
    from torchrow.engines.tracker import Tracker

    tracker = Tracker(params, device=device, hfov_deg=hfov_deg, workers=workers, camera=camera)
    sizes: dict[int, tuple[int, int] | None] = {}
    for batch in track_batches(sources, impl, params, batch_size, sizes):
        for k, res, rgb in tracker.track_iter([tapped(b) for b in batch], [names[b] for b in batch],
                                              sizes[batch[0]]):
            yield batch[k], stamped(batch[k], res), rgb


def track_batches(sources: Sequence, impl: str = "tensor", params: Params | None = None,
                  batch_size: int = 8, sizes: dict | None = None, onnx=None) -> list[list[int]]:
    """The batches :func:`track` runs: source indices grouped by their working size
    (:func:`source_size`, stored into ``sizes`` if given), in runs of up to ``batch_size``
    (one source each for the reference).

    The Ray engine sends each batch to one task, with the same ``workers``: the tensor
    tracker's float64 reductions run over the sequences of a worker's group, and a row can
    differ in its last bit (about 1e-16 relative; 2 of 100 Caterra frames between 4
    sequences in groups of 2 and one sequence alone) with another grouping.
    """
    params = params or Params()
    if impl == "reference":
        return [[b] for b in range(len(sources))]
    if impl == "onnx":  # the model's static batch; every source has the model's working size
        step = onnx.batch if onnx is not None else 1
        return [list(range(lo, min(lo + step, len(sources)))) for lo in range(0, len(sources), step)]
    groups: dict[object, list[int]] = {}
    for b, s in enumerate(sources):  # one working size per batch
        size = source_size(s, params)
        if sizes is not None:
            sizes[b] = size
        groups.setdefault(size, []).append(b)
    return [g[j:j + batch_size] for g in groups.values() for j in range(0, len(g), batch_size)]
