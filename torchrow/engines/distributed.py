"""The Ray engine: ``torchrow detect|eval|video --engine ray`` and its Python entry point.

Needs ``pip install 'torchrow[ray]'`` (Ray Data). Records agree with the local engine's
(:mod:`torchrow.engines.runner`) as ALGORITHM.md "Identical results" defines it: the workers
run the same code on the same inputs, every discrete output is equal, and floats may differ
in their last bits (seen: up to 6e-14; the contract is 1e-6) where a float sum runs over a
batch that the engines form differently.

* **Images** (:func:`run`, a drop-in for :func:`torchrow.engines.runner.run`): the inputs are
  read lazily in batches of ``batch_size`` ``(index, name, pickled loader)`` rows and sent to
  a pool of ``workers`` actors (at most :data:`BATCHES_IN_FLIGHT` batches per actor out, so
  the driver never holds a whole bag's frames), each holding one
  :class:`~torchrow.engines.detector.CropRowDetector` (built once, ``cpus_per_worker`` torch
  threads). Inside a batch the images are grouped by working size
  (:func:`torchrow.engines.runner.run`), so mixed sizes cost extra calls, never wrong results.
  Loaders run *on the workers*: they must be picklable (``functools.partial(load_image,
  path, width)``, a :class:`torchrow.core.rosbag.BagFrame`, a lambda over a path) and the paths
  must be readable there (one machine, a shared file system, or object storage read by the
  loader, see :func:`read_binary`). Results come back in input order.
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
from typing import TYPE_CHECKING

import numpy as np

from torchrow.core.camera import CameraModel
from torchrow.core.params import Params
from torchrow.core.results import ImageResult

if TYPE_CHECKING:  # imported by the workers that use them
    from torchrow.engines.detector import CropRowDetector
    from torchrow.engines.runner import Loader
    from torchrow.onnx.runtime import OnnxDetector

__all__ = ["init", "check_address", "run", "track", "read_binary", "RECORDS_PER_CHUNK", "BATCHES_IN_FLIGHT",
           "CONNECT_TIMEOUT_S"]

#: Video records per object sent back by a sequence's task.
RECORDS_PER_CHUNK = 16

#: Batches sent ahead per detector actor by :func:`run`: the driver holds at most
#: ``BATCHES_IN_FLIGHT * workers * batch_size`` inputs (a bag frame's loader holds its bytes).
BATCHES_IN_FLIGHT = 2

#: Seconds a TCP connection to a cluster's address may take before it is called unreachable
#: (``ray.init`` itself waits minutes, deaf to SIGTERM for part of it).
CONNECT_TIMEOUT_S = 3.0


def _ray():
    try:
        import ray
        import ray.data
    except ImportError:
        raise ImportError("the Ray engine needs Ray Data: pip install 'torchrow[ray]'") from None
    return ray


def check_address(address: str | None) -> None:
    """Fail fast, with a one-line ``ValueError``, on a cluster address that cannot work.

    ``address`` (else ``$RAY_ADDRESS``): ``None``, ``"auto"`` and ``"local"`` are left to Ray;
    ``"ray://HOST:PORT"`` needs the Ray client (``pip install 'ray[client]'``); for
    ``HOST:PORT`` and ``ray://HOST:PORT`` something must accept a TCP connection there within
    :data:`CONNECT_TIMEOUT_S` seconds.
    """
    import importlib.util
    import socket

    given = address or os.environ.get("RAY_ADDRESS") or None
    if given is None or given in ("auto", "local"):
        return
    what = f"--address {given}" if address else f"RAY_ADDRESS={given}"
    hostport = given
    if given.startswith("ray://"):
        if importlib.util.find_spec("grpc") is None:
            raise ValueError(f"{what}: a ray:// address needs the Ray client: pip install 'ray[client]'")
        hostport = given[len("ray://"):]
    host, sep, port = hostport.rpartition(":")
    if not sep or not port.isdigit() or not host:
        return  # a form Ray knows and this check does not: Ray decides
    try:
        socket.create_connection((host.strip("[]"), int(port)), timeout=CONNECT_TIMEOUT_S).close()
    except OSError as exc:
        raise ValueError(f"{what}: no Ray cluster answers at {host}:{port} ({exc.strerror or exc}); start one "
                         "there (ray start --head) or leave --address out for a local one") from None


def init(address: str | None = None, num_cpus: int | None = None, quiet: bool = True):
    """Connect to (or start) a Ray cluster; returns the ``ray`` module.

    An initialised Ray is kept. Otherwise ``ray.init(address=address)`` once
    :func:`check_address` passes; without an address (and without ``RAY_ADDRESS``) a local
    cluster with ``num_cpus`` (default: all) CPUs.
    """
    ray = _ray()
    if not ray.is_initialized():
        import logging

        check_address(address)
        kw: dict = dict(include_dashboard=False, logging_level=logging.WARNING if quiet else logging.INFO,
                        log_to_driver=not quiet)
        if address is None and not os.environ.get("RAY_ADDRESS"):
            kw["num_cpus"] = num_cpus
        ray.init(address=address, **kw)
    return ray


def _cluster_cpus(ray) -> int:
    return max(1, int(ray.cluster_resources().get("CPU", 1)))


class _Detect:
    """Detector actor: one detector, built once; runs batches of ``(index, name, loader)`` rows."""

    def __init__(self, impl: str, params: Params, device: str | None, model: str | None, threads: int) -> None:
        import torch

        torch.set_num_threads(threads)
        self.impl, self.params = impl, params
        self.det: CropRowDetector | OnnxDetector | None = None
        self.model_batch: int | None = None  # the ONNX model's static batch
        if impl == "tensor":
            from torchrow.engines.detector import CropRowDetector

            self.det = CropRowDetector(params, device=device, workers=threads)
        elif impl == "onnx":
            from torchrow.engines.runner import onnx_model
            from torchrow.onnx.runtime import OnnxDetector

            onnx = OnnxDetector(onnx_model(model))
            self.det, self.model_batch = onnx, onnx.batch

    def detect(self, batch: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """The remote method (an actor's ``__call__`` is not one)."""
        return self(batch)

    def __call__(self, batch: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        from torchrow.engines.runner import run

        items = [(str(n), pickle.loads(b)) for n, b in zip(batch["name"], batch["loader"])]
        bs = self.model_batch if self.model_batch is not None else max(len(items), 1)
        out = list(run(items, self.impl, self.params, batch_size=bs, progress=False, window=max(len(items), bs),
                       detector=self.det))
        return {"index": np.asarray(batch["index"], dtype=np.int64),
                "result": np.array([pickle.dumps(r) for _, _, r, _ in out], dtype=object),
                "seconds": np.array([s for _, _, _, s in out], dtype=np.float64)}


def run(items: Iterable[tuple[str, Loader]], impl: str = "tensor", params: Params | None = None,
        batch_size: int = 64, device: str | None = None, progress: bool = True, desc: str = "detect",
        model: str | None = None, total: int | None = None, workers: int | None = None,
        cpus_per_worker: int = 1, address: str | None = None
        ) -> Iterator[tuple[int, None, ImageResult, float]]:
    """:func:`torchrow.engines.runner.run` on a Ray cluster: yields ``(index, None, result, seconds)``
    in input order (no RGB comes back); a loader may return :class:`~torchrow.core.io.Evidenced`
    as there (its files are read on the worker). ``workers``: detector actors (default: the cluster's
    CPUs // ``cpus_per_worker``); ``batch_size``: inputs per call of an actor (made smaller
    for short runs, so that every worker gets a batch, when ``total`` is known).

    ``items`` is read lazily, one batch at a time: at most :data:`BATCHES_IN_FLIGHT` batches
    per actor are out (pickled loaders: a path, or a bag frame's bytes), and results come back
    in input order as they finish, so the driver's memory does not grow with the run."""
    import itertools

    from ray import cloudpickle
    from ray.util import ActorPool

    ray = init(address)
    params = params or Params()
    n_workers = workers or max(1, _cluster_cpus(ray) // cpus_per_worker)
    if total is not None:  # at least one batch per worker, so that a short (e.g. resumed) run spreads out
        batch_size = max(1, min(batch_size, -(-total // n_workers)))
    it = iter(items)

    def batches() -> Iterator[dict]:
        start = 0
        while chunk := list(itertools.islice(it, batch_size)):
            yield {"index": list(range(start, start + len(chunk))), "name": [n for n, _ in chunk],
                   "loader": [cloudpickle.dumps(loader) for _, loader in chunk]}
            start += len(chunk)

    todo = batches()
    first = next(todo, None)
    if first is None:
        return
    actor = ray.remote(num_cpus=cpus_per_worker)(_Detect)
    actors = [actor.remote(impl=impl, params=params, device=device, model=model, threads=cpus_per_worker)
              for _ in range(n_workers)]
    pool = ActorPool(actors)
    from torchrow.core.progress import progress as progress_bar

    bar = progress_bar(total if total is not None else 0, desc, progress, unit="image")
    nxt, sent, out = 0, 0, 0  # results yielded, inputs sent, batches sent and not yet back

    def back() -> Iterator[tuple[int, None, ImageResult, float]]:
        nonlocal nxt, out
        res = pool.get_next()  # batches come back in the order they were sent
        out -= 1
        for i, blob, sec in zip(res["index"], res["result"], res["seconds"]):
            if int(i) != nxt:
                raise RuntimeError(f"Ray returned input {int(i)} where {nxt} was due")
            bar.update(1)
            yield nxt, None, pickle.loads(blob), float(sec)
            nxt += 1

    try:
        for batch in itertools.chain([first], todo):
            pool.submit(lambda a, b: a.detect.remote(b), batch)
            sent += len(batch["index"])
            out += 1
            del batch
            if out >= BATCHES_IN_FLIGHT * n_workers:
                yield from back()
        while out:
            yield from back()
    finally:
        bar.close()
        for a in actors:
            ray.kill(a)
    if nxt != sent:
        raise RuntimeError(f"Ray returned {nxt} of {sent} results")


def _track_task(paths: list[str], topic: str | None, names: list[str], impl: str, params: Params,
                device: str | None, hfov_deg: float | None, skip: list[frozenset], workers: int,
                camera: CameraModel | None = None):
    """One batch of sequences, on a worker: yields lists of up to RECORDS_PER_CHUNK
    ``(position in the batch, record)``."""
    import torch

    from torchrow.core.frames import open_source
    from torchrow.engines.runner import track as track_local

    torch.set_num_threads(max(1, min(workers, len(paths))))
    srcs = [open_source(p, topic=topic) for p in paths]
    chunk: list[tuple[int, dict]] = []
    for b, res, _ in track_local(srcs, names, impl, params, max(len(srcs), 1), device, hfov_deg, workers,
                                 camera=camera):
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
          workers: int | None = None, address: str | None = None,
          camera: CameraModel | None = None) -> Iterator[tuple[int, dict]]:
    """Track every source (folder, video file or ROS bag, :func:`torchrow.core.frames.open_source`)
    on a Ray cluster; yields ``(source index, record)`` as records arrive (frame order within
    a source).

    One Ray task per batch of :func:`torchrow.engines.runner.track_batches` (the local engine's
    batches: sources of one working size, up to ``batch_size``), so that a sequence's float
    sums run over the same group as there (records within the contract of the module
    docstring; in practice equal); each task runs its batch in groups on ``workers`` threads
    (default: this process's torch thread count, the local engine's grouping) and reserves
    one CPU per group. ``batch_size=1`` gives one task per sequence, the most parallel (rows
    may then differ from a local batched run in a last bit, see ``track_batches``).
    ``skip[i]``: frame indices of source ``i`` not to return (resume). ``camera``: the records'
    metric steering (:class:`~torchrow.engines.tracker.Tracker`).
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
        [frozenset((skip or {}).get(i, ())) for i in batch], workers, camera): batch for batch in batches}
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


def read_binary(uri: str | Sequence[str], width: int | None = None, max_pixels: int | None = None
                ) -> Iterator[tuple[str, Callable[[], np.ndarray]]]:
    """Items for :func:`run` from files on any file system pyarrow knows (local paths,
    ``s3://bucket/prefix/``, ``gs://...``): each loader reads its file *on the worker*
    (:func:`pyarrow.fs.FileSystem.from_uri`) and decodes it as :func:`torchrow.core.io.load_image`
    does, with the same bounds (``max_pixels``: ``Params.max_pixels`` of the run; the file size
    checked before the bytes are read). A folder URI lists its image files (sorted)."""
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
                yield Path(f).name, _RemoteFile(prefix + f if prefix else f, width, max_pixels)
        else:
            yield Path(path).name, _RemoteFile(u, width, max_pixels)


class _RemoteFile:
    """Picklable loader: read a file (local path or URI) and decode it to working size."""

    def __init__(self, uri: str, width: int | None, max_pixels: int | None = None) -> None:
        self.uri, self.width, self.max_pixels = uri, width, max_pixels

    def __call__(self) -> np.ndarray:
        from torchrow.core.io import ImageError, check_file_size, decode_image

        if "://" in self.uri:
            import pyarrow.fs as pafs

            fs, path = pafs.FileSystem.from_uri(self.uri)
            try:
                size = fs.get_file_info(path).size
                if size is not None:  # load_image's bound, before reading
                    check_file_size(size, self.uri)
                with fs.open_input_stream(path) as fh:
                    data = fh.read()
            except OSError as exc:
                raise ImageError(f"cannot read {self.uri}: {exc}") from None
            return decode_image(data, self.width, self.max_pixels, what=self.uri)
        from torchrow.core.io import load_image

        return load_image(self.uri, self.width, self.max_pixels)
