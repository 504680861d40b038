"""onnxruntime runners of exported models: :class:`OnnxDetector` (the image-mode detector,
results equal :class:`torchrow.CropRowDetector`'s) and :class:`OnnxTracker` (the tracker step,
results equal :class:`torchrow.Tracker`'s), with onnxruntime's pre-optimised copy of a model
cached on disk (:func:`ort_optimized`).

What runs where for the detector:

* host, before the graph: section 2 (vegetation colour: colour clustering has data-dependent
  shapes) with :func:`torchrow.functional.color.vegetation_color`, and the colour's LAB from
  the shared table (graph input ``veg_lab``, float64 ``(B, 3)``);
* graph (:class:`torchrow.onnx.graphs.StaticDetector`): sky, LAB box, bushy removal, Canny,
  Hough votes and the line search with outliers and restarts, vanishing point, RANSAC band
  points, scoring and the weighted moments of the best hypothesis' inliers;
* host, after the graph: the principal direction (``atan2``, ``cos``, ``sin``: ONNX has no
  ``Atan2``, onnxruntime's ``Atan`` is float32-only) and the row validity of 7.6 on ``B x
  n_rows`` numbers (:func:`torchrow.onnx.graphs.finish_rows`).

For the tracker step see :class:`torchrow.onnx.graphs.StaticTrackerStep`.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from torchrow.core.batch import BatchResult
from torchrow.core.camera import CameraModel
from torchrow.core.params import Params
from torchrow.core.results import concat_batches
from torchrow.core.steering import check_optics
from torchrow.onnx.metadata import model_meta

__all__ = ["OnnxDetector", "OnnxTracker", "ort_optimized", "session_options", "import_ort", "ORT_CACHE_KEEP"]

def import_ort():
    """The ``onnxruntime`` module, or an ``ImportError`` naming the extra that installs it."""
    try:
        import onnxruntime as ort
    except ImportError:  # pragma: no cover - depends on the environment
        raise ImportError("onnxruntime is not installed: pip install 'torchrow[onnx]'") from None
    return ort


class OnnxRunner:
    """What :func:`_open` sets on both runners from the model's metadata: the onnxruntime
    ``session``, the model's ``path``, its working ``height x width``, static ``batch`` and the
    ``params`` it was exported with."""

    session: Any  # onnxruntime.InferenceSession
    path: Path
    height: int
    width: int
    batch: int
    params: Params


class OnnxDetector(OnnxRunner):
    """Run an exported detector in onnxruntime; results equal :class:`CropRowDetector`'s.

    Parameters
    ----------
    model_path : str or Path
        A model written by :func:`to_onnx`.
    threads : int, optional
        onnxruntime intra-op threads (default: onnxruntime's choice).
    cache : bool
        Open onnxruntime's pre-optimised copy of the model (:func:`ort_optimized`; written
        on the first open): the session opens in about half the time.

    Notes
    -----
    Graph optimisations are limited to onnxruntime's *basic* level (constant folding and
    redundant-node removal); the extended levels may fuse float64 multiply-adds, which would
    change the rounding the spec prescribes.
    """

    def __init__(self, model_path: str | Path, threads: int | None = None, cache: bool = True) -> None:
        _open(self, model_path, "detector", threads, cache)

    def __call__(self, images: torch.Tensor, veg_color: torch.Tensor | None = None) -> BatchResult:
        """Detect rows in ``uint8 (N, 3, H, W)`` images (any ``N``; run in batches of the
        model's ``B``, the last one padded). ``veg_color`` ``uint8 (N, 3)`` or ``(3,)``
        replaces the per-image colour clustering, as for :class:`CropRowDetector`."""
        from torchrow.core.tables import lab_table_torch, pack_rgb
        from torchrow.functional import color as fcolor
        from torchrow.functional._checks import check_images

        check_images(images)
        n, _, h, w = images.shape
        if (h, w) != (self.height, self.width):
            raise ValueError(f"the model {self.path.name} takes {self.width}x{self.height} images, "
                             f"got {w}x{h} (export one with --width {w} --height {h})")
        images = images.cpu().contiguous()
        if veg_color is None:
            color = fcolor.vegetation_color(images, self.params) if n else torch.zeros((0, 3), dtype=torch.uint8)
        else:
            color = fcolor.color_override(veg_color, n, torch.device("cpu"))
        lab = lab_table_torch("cpu")[torch.from_numpy(pack_rgb(color.numpy()))].clone()
        parts = []
        for s0 in range(0, max(n, 1), self.batch):
            x = images[s0:s0 + self.batch]
            c = lab[s0:s0 + self.batch]
            m = x.shape[0]
            if m < self.batch:  # pad the last batch by repeating an image (or zeros)
                fill = self.batch - m
                x = torch.cat([x, torch.zeros((fill, 3, h, w), dtype=torch.uint8)])
                c = torch.cat([c, torch.zeros((fill, 3), dtype=torch.float64)])
            outs = self.session.run(None, {"images": x.numpy(), "veg_lab": c.numpy()})
            parts.append(self._result([torch.from_numpy(o[:m]) for o in outs], color[s0:s0 + m]))
        return concat_batches(parts)

    def _result(self, outs: list[torch.Tensor], color: torch.Tensor) -> BatchResult:
        from torchrow.functional import ransac as fransac
        from torchrow.onnx.graphs import GRAPH_OUTPUTS, finish_rows

        o = dict(zip(GRAPH_OUTPUTS, outs))
        p = self.params
        b = color.shape[0]
        rows = finish_rows(o, self.height, self.width, p)
        i64: dict[str, Any] = dict(dtype=torch.int64)
        status = fransac.image_status(rows, o["has_vp"], o["has_veg"])
        return BatchResult.build(self.width, self.height, p.theta_step, rows=rows, fields=o, status=status,
                                 veg_color=color, k=torch.full((b,), p.veg_tol, **i64))

    def detect(self, images: Sequence[np.ndarray]) -> BatchResult:
        """Detect rows in a list of same-sized working-size RGB arrays ``(H, W, 3)``."""
        x = torch.from_numpy(np.stack(images)).permute(0, 3, 1, 2).contiguous()
        return self(x)


#: Pre-optimised models kept in the cache folder (the oldest beyond this are deleted).
ORT_CACHE_KEEP = 8


def ort_optimized(path: str | Path) -> Path | None:
    """onnxruntime's basic-level optimisation of the model ``path``, cached on disk.

    onnxruntime optimises a graph every time a session opens it (about half of the open
    time: 0.5 of 1.0 s for the default tracker). The optimised graph is written once, under
    ``TORCHROW_CACHE`` (or ``~/.cache/torchrow``) in ``ort/``, keyed by the SHA-256 of the
    model file and the onnxruntime version, and later opens load it with optimisations
    disabled: the same graph onnxruntime would run, so the same results (checked on every
    CRBD image and Caterra frame in ``benchmarks/``). Returns ``None`` (open the original with
    basic optimisations) when the folder cannot be written; ``TORCHROW_ORT_CACHE=0``
    disables the cache.
    """
    import hashlib
    import os

    if os.environ.get("TORCHROW_ORT_CACHE", "1") == "0":
        return None
    ort = import_ort()
    from torchrow.core.tables import cache_dir

    digest = hashlib.sha256(Path(path).read_bytes())
    digest.update(ort.__version__.encode())
    folder = cache_dir() / "ort"
    out = folder / f"{digest.hexdigest()[:32]}.onnx"
    if out.is_file():
        os.utime(out)  # recently used: kept by the pruning below
        return out
    try:
        folder.mkdir(parents=True, exist_ok=True)
        tmp = folder / f".{out.name}.{os.getpid()}.tmp"
        so = ort.SessionOptions()
        so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_BASIC
        so.log_severity_level = 3
        so.optimized_model_filepath = str(tmp)
        ort.InferenceSession(str(path), so, providers=["CPUExecutionProvider"])
        os.replace(tmp, out)
        old = sorted(folder.glob("*.onnx"), key=lambda f: f.stat().st_mtime, reverse=True)[ORT_CACHE_KEEP:]
        for f in old:
            f.unlink(missing_ok=True)
    except OSError:
        return None
    return out


def session_options(threads: int | None, optimized: bool = False) -> Any:
    """The ``onnxruntime.SessionOptions`` torchrow's runners open their models with: errors only,
    no spin-waiting, ``threads`` intra-op threads (``None``: onnxruntime's choice), and basic
    graph optimisations, none where the model is already :func:`ort_optimized` (``optimized``)."""
    ort = import_ort()
    so = ort.SessionOptions()
    so.log_severity_level = 3  # errors only: normal use prints nothing
    # no spin-waiting between operations: this graph's many small nodes left onnxruntime's
    # second thread spinning while the host's frame reader or colour clustering wanted the core
    # (tracker step 65-72 -> 58-62 ms per frame with frames read ahead; the detector no slower)
    so.add_session_config_entry("session.intra_op.allow_spinning", "0")
    if threads:
        so.intra_op_num_threads = int(threads)
    # basic optimisations only: no fusions that could change float64 rounding
    so.graph_optimization_level = (ort.GraphOptimizationLevel.ORT_DISABLE_ALL if optimized
                                   else ort.GraphOptimizationLevel.ORT_ENABLE_BASIC)
    return so


def _open(runner: OnnxRunner, model_path: str | Path, kind: str, threads: int | None, cache: bool = True) -> None:
    """Check ``model_path`` (present, a ``kind`` model), open an onnxruntime session on
    ``runner.session`` (from the :func:`ort_optimized` copy when ``cache``) and set
    ``runner.path``, ``height``, ``width``, ``batch``, ``params``."""
    ort = import_ort()
    path = Path(model_path)
    if not path.is_file():
        raise FileNotFoundError(f"ONNX model not found: {path}")
    info = model_meta(path)
    if info["kind"] != kind:
        other = {"detector": "OnnxDetector", "tracker": "OnnxTracker"}[info["kind"]]
        raise ValueError(f"{path.name} is a torchrow {info['kind']} model; run it with {other}")
    ready = ort_optimized(path) if cache else None
    runner.session = ort.InferenceSession(str(ready or path), session_options(threads, optimized=ready is not None),
                                          providers=["CPUExecutionProvider"])
    runner.path = path
    runner.height, runner.width, runner.batch = info["height"], info["width"], info["batch"]
    runner.params = info["params"]


class OnnxTracker(OnnxRunner):
    """Run an exported tracker step (``to_onnx(..., tracker=True)``) in onnxruntime.

    Same interface and results as :class:`torchrow.Tracker` for ``B`` sequences in
    lock-step, ``B`` the model's static batch: :meth:`forward` (tensors) and :meth:`step`
    (arrays in, :class:`~torchrow.core.steering.FrameResult` records out). The host computes only
    what a sequence needs once, on its frame 0: the vegetation colour (section 2), its ``k``
    table (:func:`~torchrow.functional.vegetation.min_k_table`, about 30 ms, rebuilt only when
    a slot's colour changes) and the sky (section 1); everything else, frame 0's ``info0``
    included, runs in the graph.

    A model exported in improved mode (:class:`torchrow.onnx.graphs.StaticLatticeStep`, the
    lattice tracker of ALGORITHM.md 11.7) runs as :class:`torchrow.Tracker` in improved
    mode: :meth:`forward` returns ``(LatticeStep, LatticeTrackerState)`` and the records carry
    the lattice tracker's fields; the host computes nothing (:attr:`improved` is ``True``).

    Parameters
    ----------
    model_path : str or Path
    hfov_deg : float, optional
        Horizontal field of view for the records' ``heading_rad``.
    camera : CameraModel, optional
        For the records' ``lateral_m``, ``spacing_m`` and ground ``heading_rad`` (as
        :class:`torchrow.Tracker`); not with ``hfov_deg``.
    threads : int, optional
        onnxruntime intra-op threads.
    cache : bool
        Open onnxruntime's pre-optimised copy of the model, as :class:`OnnxDetector`.
    """

    def __init__(self, model_path: str | Path, hfov_deg: float | None = None, threads: int | None = None,
                 cache: bool = True, camera: CameraModel | None = None) -> None:
        check_optics(hfov_deg, camera)
        _open(self, model_path, "tracker", threads, cache)
        self.hfov_deg = hfov_deg
        self.camera = camera
        #: the model is the lattice tracker step (improved mode)
        self.improved = self.params.mode == "improved"
        if self.improved:
            from torchrow.onnx.graphs import LATTICE_INPUTS

            names = tuple(i.name for i in self.session.get_inputs())
            if names != LATTICE_INPUTS:
                missing = sorted(set(LATTICE_INPUTS) - set(names)) or sorted(set(names) - set(LATTICE_INPUTS))
                raise ValueError(f"{self.path.name} is a lattice tracker model of another torchrow version (its "
                                 f"inputs differ: {', '.join(missing) or 'their order'}); export it again with "
                                 "`torchrow export onnx --tracker --mode improved`")
            return
        if self.session.get_inputs()[1].name != "k_table":
            raise ValueError(f"{self.path.name} is a tracker model of an older torchrow (it takes veg_lab, not "
                             "k_table); export it again with `torchrow export onnx --tracker`")
        n_k = self.params.video_k_max - self.params.video_k_min + 1
        self._table = np.full((self.batch, 1 << 24), n_k, dtype=np.uint8)  # the graph's k_table feed
        self._table_color: list = [None] * self.batch  # the colour each slot's table row holds

    def _k_tables(self, color: torch.Tensor) -> np.ndarray:
        """The ``k_table`` feed for the sequences' colours ``uint8 (B, 3)``: each slot's row is
        rebuilt (:func:`~torchrow.functional.vegetation.min_k_table`) only when its colour
        changes, i.e. when a sequence starts on that slot with another colour."""
        from torchrow.functional.vegetation import min_k_table

        for b, c in enumerate(color.tolist()):
            if self._table_color[b] != c:
                self._table[b] = min_k_table(color[b:b + 1], self.params)[0].numpy()
                self._table_color[b] = c
        return self._table

    def forward(self, frames: torch.Tensor, state=None, active: torch.Tensor | None = None):
        """One lock-step frame: ``uint8 (B, 3, H, W)`` frames at working size ->
        ``(TrackStep, TrackerState)`` (improved mode: ``(LatticeStep, LatticeTrackerState)``),
        as :meth:`torchrow.Tracker.forward`."""
        from torchrow.functional._checks import check_images

        check_images(frames, "frames")
        b, _, h, w = frames.shape
        if (b, h, w) != (self.batch, self.height, self.width):
            raise ValueError(f"the model {self.path.name} takes {self.batch} frames of {self.width}x{self.height}, "
                             f"got {b} of {w}x{h}")
        x = frames.cpu().contiguous()
        act = torch.ones(b, dtype=torch.bool) if active is None else active.to("cpu", torch.bool)
        if self.improved:
            return self._lattice_forward(x, state, act)
        from torchrow.functional import color as fcolor
        from torchrow.functional import sky as fsky
        from torchrow.functional.tracking import TrackerState, TrackStep
        from torchrow.onnx.graphs import TRACKER_STATE, TRACKER_STEP

        state = state if state is not None else TrackerState.empty(b, self.params)
        color = state.veg_color.clone()
        sky = state.sky.clone()
        start = act & ~state.ready
        if bool(start.any()):
            idx = torch.nonzero(start).view(-1)  # host side: which sequences begin now
            first = x.index_select(0, idx)
            color[idx] = fcolor.vegetation_color(first, self.params)
            sky[idx] = fsky.sky_row(first, self.params).to(torch.int64)
        feed = {"images": x.numpy(), "k_table": self._k_tables(color), "active": act.numpy()}
        feed.update({"state_" + f: getattr(state, f).cpu().numpy() for f in TRACKER_STATE})
        feed["state_sky"] = sky.numpy()
        outs = [torch.from_numpy(o) for o in self.session.run(None, feed)]
        step = TrackStep(**dict(zip(TRACKER_STEP, outs)), active=act)
        new = TrackerState(veg_color=color, **{f: o for f, o in zip(TRACKER_STATE, outs[len(TRACKER_STEP):])})
        return step, new

    def _lattice_forward(self, x: torch.Tensor, state, act: torch.Tensor):
        """:meth:`forward` of a lattice tracker step: the state in, the graph's outputs back as
        the step and the new state (:func:`~torchrow.onnx.graphs.lattice_results`)."""
        from torchrow.functional.lattice_tracking import LatticeTrackerState
        from torchrow.onnx.graphs import LATTICE_STATE, lattice_results

        state = state if state is not None else LatticeTrackerState.empty(self.batch)
        if not isinstance(state, LatticeTrackerState):
            raise TypeError(f"the lattice tracker model {self.path.name} takes a LatticeTrackerState, "
                            f"got {type(state).__name__}")
        feed = {"images": x.numpy(), "active": act.numpy()}
        feed.update({"state_" + f: getattr(state, f).cpu().numpy() for f in LATTICE_STATE})
        return lattice_results([torch.from_numpy(o) for o in self.session.run(None, feed)], act)

    __call__ = forward

    def step(self, frames, state=None, names=None):
        """Arrays (any size, resized to the working width) or a working-size tensor in;
        ``(list of FrameResult, TrackerState)`` out, as :meth:`torchrow.Tracker.step`."""
        if isinstance(frames, torch.Tensor):
            x = frames
        else:
            from torchrow.core.frames import prepare_frame

            x = torch.from_numpy(np.stack([prepare_frame(f, self.params.video_width, self.params.max_pixels)
                                           for f in frames])).permute(0, 3, 1, 2)
        stepped, new = self.forward(x.contiguous(), state)
        return self.results(stepped, new, x.shape[3], x.shape[2], names), new

    def results(self, stepped, state, width: int, height: int, names=None, sources=None, indices=None):
        """Per-sequence :class:`~torchrow.core.steering.FrameResult` of a step (``None`` for
        inactive sequences), as :meth:`torchrow.Tracker.results`: the records of
        :func:`torchrow.functional.tracking.records`, or in improved mode of
        :func:`torchrow.functional.lattice_tracking.records`."""
        from torchrow.functional import lattice_tracking, tracking

        fn = lattice_tracking.records if self.improved else tracking.records
        return fn(stepped, state, width, height, self.params, self.hfov_deg, names, sources, indices,
                  camera=self.camera)

    def track_iter(self, sequences, sources=None):
        """Track up to ``B`` (the model's batch) sequences in lock-step, lazily, as
        :meth:`torchrow.Tracker.track_iter`: yields ``(sequence index, FrameResult, working
        RGB or None)``; unreadable frames and frames of another working size than the
        model's get ``error`` records. Slots without a sequence, or whose sequence has ended
        or has no readable frame now, are fed as inactive (they keep their state)."""
        from torchrow.functional.tracking import lockstep

        n = len(sequences)
        if n > self.batch:
            raise ValueError(f"the model {self.path.name} tracks {self.batch} sequence(s) at once, got {n}")
        state = None
        h, w = self.height, self.width

        def step(chunk):
            nonlocal state
            for t in range(chunk.length):
                act = np.array(chunk.active(t) + [False] * (self.batch - n))
                if not act.any():
                    yield None
                    continue
                frames = np.zeros((self.batch, h, w, 3), dtype=np.uint8)
                for b in np.flatnonzero(act):
                    frames[b] = chunk.rgb(b, t)
                x = torch.from_numpy(frames).permute(0, 3, 1, 2).contiguous()
                stepped, state = self.forward(x, state, torch.from_numpy(act))
                yield stepped, state

        return lockstep(sequences, step, self.params, size=(h, w), sources=sources, hfov_deg=self.hfov_deg,
                        camera=self.camera, size_note=f" (the size the model {self.path.name} takes)",
                        records_fn=self.results)
