"""The Ray engine: ``torchrow detect|eval|video --engine ray`` and its Python entry point.

Needs ``pip install 'torchrow[ray]'`` (Ray Data). Records are identical to the local
engine's (:mod:`torchrow.engines.runner`): the workers run the same code on the same inputs, and an
image's or a sequence's result never depends on what else is in its batch.

* **Images** (:func:`run`, a drop-in for :func:`torchrow.engines.runner.run`): the inputs become a
  Ray dataset of ``(index, name, pickled loader)`` rows; ``map_batches`` runs them on an
  actor pool of ``workers`` actors, each holding one
  :class:`~torchrow.engines.detector.CropRowDetector` (built once, ``cpus_per_worker`` torch
  threads). Inside a batch of ``batch_size`` rows the images are grouped by working size
  (:func:`torchrow.engines.runner.run`), so mixed sizes cost extra calls, never wrong results.
  Loaders run *on the workers*: they must be picklable (``functools.partial(load_image,
  path, width)``, a :class:`torchrow.core.rosbag.BagFrame`, a lambda over a path) and the paths
  must be readable there (one machine, a shared file system, or object storage read by the
  loader, see :func:`read_binary`). Results come back in input order
  (``preserve_order``), as Ray's streaming executor produces them.
* **Video** (:func:`track`): one Ray task (a streaming generator) per batch of sequences
  that the local engine would track together (``batch_size`` 1: one task per sequence); it
  opens its sources itself and runs :func:`torchrow.engines.runner.track` on them; records of a
  sequence come back in frame order, tasks interleaved as they finish chunks.

``address``: ``None`` joins the cluster of ``RAY_ADDRESS`` if set, else starts a local one
with this machine's CPUs; ``"auto"`` or ``"HOST:6379"`` joins a running one (``ray start
--head``); ``"ray://HOST:10001"`` connects as a Ray client. A Ray already initialised in
this process is used as it is.
"""

from __future__ import annotations

import os
import pickle
from collections.abc import Callable, Iterable, Iterator, Sequence
from pathlib import Path

import numpy as np

from torchrow.core.params import Params
from torchrow.core.results import ImageResult

__all__ = ["init", "run", "track", "read_binary", "RECORDS_PER_CHUNK"]

#: Video records per object sent back by a sequence's task.
RECORDS_PER_CHUNK = 16


def _ray():
    try:
        import ray
        import ray.data
    except ImportError:
        raise ImportError("the Ray engine needs Ray Data: pip install 'torchrow[ray]'") from None
    return ray


def init(address: str | None = None, num_cpus: int | None = None, quiet: bool = True):
    """Connect to (or start) a Ray cluster; returns the ``ray`` module.

    An initialised Ray is kept. Otherwise ``ray.init(address=address)``; without an address
    (and without ``RAY_ADDRESS``) a local cluster with ``num_cpus`` (default: all) CPUs.
    """
    ray = _ray()
    if not ray.is_initialized():
        import logging

        kw: dict = dict(include_dashboard=False, logging_level=logging.WARNING if quiet else logging.INFO,
                        log_to_driver=not quiet)
        if address is None and not os.environ.get("RAY_ADDRESS"):
            kw["num_cpus"] = num_cpus
        ray.init(address=address, **kw)
    return ray


def _cluster_cpus(ray) -> int:
    return max(1, int(ray.cluster_resources().get("CPU", 1)))


class _Detect:
    """Ray Data actor: one detector, built once; runs batches of ``(index, name, loader)`` rows."""

    def __init__(self, impl: str, params: Params, device: str | None, model: str | None, threads: int) -> None:
        import torch

        torch.set_num_threads(threads)
        self.impl, self.params = impl, params
        self.det = None
        if impl == "tensor":
            from torchrow.engines.detector import CropRowDetector

            self.det = CropRowDetector(params, device=device, workers=threads)
        elif impl == "onnx":
            from torchrow.onnx.runtime import OnnxDetector

            self.det = OnnxDetector(model)

    def __call__(self, batch: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        from torchrow.engines.runner import run

        items = [(str(n), pickle.loads(b)) for n, b in zip(batch["name"], batch["loader"])]
        bs = self.det.batch if self.impl == "onnx" else max(len(items), 1)
        out = list(run(items, self.impl, self.params, batch_size=bs, progress=False, window=max(len(items), bs),
                       detector=self.det))
        return {"index": np.asarray(batch["index"], dtype=np.int64),
                "result": np.array([pickle.dumps(r) for _, _, r, _ in out], dtype=object),
                "seconds": np.array([s for _, _, _, s in out], dtype=np.float64)}


def run(items: Iterable[tuple[str, Callable[[], np.ndarray]]], impl: str = "tensor", params: Params | None = None,
        batch_size: int = 64, device: str | None = None, progress: bool = True, desc: str = "detect",
        model: str | None = None, total: int | None = None, workers: int | None = None,
        cpus_per_worker: int = 1, address: str | None = None
        ) -> Iterator[tuple[int, None, ImageResult, float]]:
    """:func:`torchrow.engines.runner.run` on a Ray cluster: yields ``(index, None, result, seconds)``
    in input order (no RGB comes back). ``workers``: actors in the pool (default: the
    cluster's CPUs // ``cpus_per_worker``); ``batch_size``: rows per ``map_batches`` call
    (made smaller for short runs, so that every worker gets a batch). The driver holds one
    row per input (name and pickled loader, a few hundred bytes) and the results that
    arrive ahead of an earlier one; Ray's streaming executor bounds the rest."""
    from ray import cloudpickle

    ray = init(address)
    params = params or Params()
    rows = [{"index": i, "name": name, "loader": cloudpickle.dumps(loader)} for i, (name, loader) in enumerate(items)]
    if not rows:
        return
    n_workers = workers or max(1, _cluster_cpus(ray) // cpus_per_worker)
    # DataContext is per process: set what this run needs, put the caller's values back after
    ctx = ray.data.DataContext.get_current()
    saved = (ctx.execution_options.preserve_order, ctx.enable_progress_bars)
    ctx.execution_options.preserve_order = True
    ctx.enable_progress_bars = progress
    # at least one block per worker, so that a short (e.g. resumed) run still spreads out
    batch_size = max(1, min(batch_size, -(-len(rows) // n_workers)))
    blocks = max(1, min(len(rows), -(-len(rows) // batch_size)))
    ds = ray.data.from_items(rows, override_num_blocks=blocks)
    ds = ds.map_batches(_Detect, batch_size=batch_size, batch_format="numpy", concurrency=n_workers,
                        num_cpus=cpus_per_worker, fn_constructor_kwargs=dict(
                            impl=impl, params=params, device=device, model=model, threads=cpus_per_worker))
    from torchrow.core.progress import progress as progress_bar

    bar = progress_bar(total if total is not None else len(rows), desc, progress, unit="image")
    waiting: dict[int, tuple[ImageResult, float]] = {}
    nxt = 0
    try:
        for batch in ds.iter_batches(batch_size=None, batch_format="numpy"):
            for i, blob, sec in zip(batch["index"], batch["result"], batch["seconds"]):
                waiting[int(i)] = (pickle.loads(blob), float(sec))
            while nxt in waiting:  # preserve_order keeps input order; this only guards it
                res, sec = waiting.pop(nxt)
                bar.update(1)
                yield nxt, None, res, sec
                nxt += 1
    finally:
        bar.close()
        ctx.execution_options.preserve_order, ctx.enable_progress_bars = saved
    if nxt != len(rows):
        raise RuntimeError(f"Ray returned {nxt} of {len(rows)} results")


def _track_task(paths: list[str], topic: str | None, names: list[str], impl: str, params: Params,
                device: str | None, hfov_deg: float | None, skip: list[frozenset], workers: int):
    """One batch of sequences, on a worker: yields lists of up to RECORDS_PER_CHUNK
    ``(position in the batch, record)``."""
    import torch

    from torchrow.core.frames import open_source
    from torchrow.engines.runner import track as track_local

    torch.set_num_threads(max(1, min(workers, len(paths))))
    srcs = [open_source(p, topic=topic) for p in paths]
    chunk: list[tuple[int, dict]] = []
    for b, res, _ in track_local(srcs, names, impl, params, max(len(srcs), 1), device, hfov_deg, workers):
        if res.frame in skip[b]:
            continue
        chunk.append((b, res.to_record()))
        if len(chunk) >= RECORDS_PER_CHUNK:
            yield chunk
            chunk = []
    if chunk:
        yield chunk


def track(sources: Sequence[str | Path], names: Sequence[str] | None = None, impl: str = "tensor",
          params: Params | None = None, device: str | None = None, hfov_deg: float | None = None,
          topic: str | None = None, skip: dict[int, set[int]] | None = None, batch_size: int = 8,
          workers: int | None = None, address: str | None = None) -> Iterator[tuple[int, dict]]:
    """Track every source (folder, video file or ROS bag, :func:`torchrow.core.frames.open_source`)
    on a Ray cluster; yields ``(source index, record)`` as records arrive (frame order within
    a source).

    One Ray task per batch of :func:`torchrow.engines.runner.track_batches` (the local engine's
    batches: sources of one working size, up to ``batch_size``), so that records are the
    local engine's bit for bit; each task runs its batch in groups on ``workers`` threads
    (default: this process's torch thread count, the local engine's grouping) and reserves
    one CPU per group. ``batch_size=1`` gives one task per sequence, the most parallel (rows
    may then differ from a local batched run in a last bit, see ``track_batches``).
    ``skip[i]``: frame indices of source ``i`` not to return (resume).
    """
    import torch

    from torchrow.core.frames import open_source
    from torchrow.engines.runner import track_batches

    ray = init(address)
    params = params or Params()
    names = [str(s) for s in sources] if names is None else list(names)
    batches = track_batches([open_source(s, topic=topic) for s in sources], impl, params, batch_size)
    workers = workers or torch.get_num_threads()
    task = ray.remote(num_returns="streaming")(_track_task)
    cpus = _cluster_cpus(ray)
    gens = {task.options(num_cpus=min(cpus, max(1, min(workers, len(batch))) if impl == "tensor" else 1)).remote(
        [str(sources[i]) for i in batch], topic, [names[i] for i in batch], impl, params, device, hfov_deg,
        [frozenset((skip or {}).get(i, ())) for i in batch], workers): batch for batch in batches}
    while gens:
        ready, _ = ray.wait(list(gens), num_returns=1)
        for gen in ready:
            try:
                ref = next(gen)
            except StopIteration:
                del gens[gen]
                continue
            for b, rec in ray.get(ref):
                yield gens[gen][b], rec


def read_binary(uri: str | Sequence[str], width: int | None = None) -> Iterator[tuple[str, Callable[[], np.ndarray]]]:
    """Items for :func:`run` from files on any file system pyarrow knows (local paths,
    ``s3://bucket/prefix/``, ``gs://...``): each loader reads its file *on the worker*
    (:func:`pyarrow.fs.FileSystem.from_uri`) and decodes it as :func:`torchrow.core.io.load_image`.
    A folder URI lists its image files (sorted)."""
    import pyarrow.fs as pafs

    from torchrow.core.io import IMAGE_EXTENSIONS

    uris = [uri] if isinstance(uri, str) else list(uri)
    for u in uris:
        fs, path = pafs.FileSystem.from_uri(u) if "://" in u else (pafs.LocalFileSystem(), str(Path(u).resolve()))
        info = fs.get_file_info(path)
        if info.type == pafs.FileType.Directory:
            found = fs.get_file_info(pafs.FileSelector(path, recursive=False))
            files = sorted(f.path for f in found if f.type == pafs.FileType.File
                           and Path(f.path).suffix.lower() in IMAGE_EXTENSIONS)
            prefix = u.split("://", 1)[0] + "://" if "://" in u else ""
            for f in files:
                yield Path(f).name, _RemoteFile(prefix + f if prefix else f, width)
        else:
            yield Path(path).name, _RemoteFile(u, width)


class _RemoteFile:
    """Picklable loader: read a file (local path or URI) and decode it to working size."""

    def __init__(self, uri: str, width: int | None) -> None:
        self.uri, self.width = uri, width

    def __call__(self) -> np.ndarray:
        from torchrow.core.io import ImageError, decode_image

        if "://" in self.uri:
            import pyarrow.fs as pafs

            fs, path = pafs.FileSystem.from_uri(self.uri)
            try:
                with fs.open_input_stream(path) as fh:
                    data = fh.read()
            except OSError as exc:
                raise ImageError(f"cannot read {self.uri}: {exc}") from None
            return decode_image(data, self.width, what=self.uri)
        from torchrow.core.io import load_image

        return load_image(self.uri, self.width)
