"""ONNX export (torchrow.onnx): op list, onnxruntime parity with the tensor path, CLI.

The exported graph takes minutes to build on a small CPU, so the model of these tests is
exported once and cached on disk (``TORCHROW_CACHE`` or ``~/.cache/torchrow``), keyed by
the source of the code that defines it; parameters with fewer line-search steps
(``n_rows=3, max_outliers=2``: 16 steps instead of 59) keep it small. Full-CRBD parity at
the default parameters is the ``slow`` test at the end (and ``benchmarks/bench_onnx.py``).
"""

from __future__ import annotations

import contextlib
import json
from pathlib import Path

import numpy as np
import pytest
import torch

pytest.importorskip("onnxruntime")
pytest.importorskip("onnx")
pytest.importorskip("onnxscript")

from onnx_models import ALLOWED_OPS
from onnx_models import exported as _exported

from torchrow import Params
from torchrow.apps.cli import main
from torchrow.engines.detector import CropRowDetector
from torchrow.evaluation.synthetic import FieldSpec, sequence
from torchrow.onnx.export import to_onnx
from torchrow.onnx.metadata import model_info
from torchrow.onnx.passes import FORBIDDEN_OPS, op_counts
from torchrow.onnx.runtime import OnnxDetector

SMALL = Params(n_rows=3, max_outliers=2)
BATCH = 2


@pytest.fixture(scope="module")
def model_path(tmp_path_factory) -> Path:
    return _exported(SMALL, BATCH, tmp_path_factory.mktemp("onnx"))


@pytest.fixture(scope="module")
def runner(model_path: Path) -> OnnxDetector:
    return OnnxDetector(model_path)


def _same(ref, got, tol: float = 1e-4) -> list[str]:
    """Differences between two lists of ImageResult: discrete fields equal, rows within tol px."""
    problems = []
    for i, (a, b) in enumerate(zip(ref, got)):
        ra, rb = a.to_record(), b.to_record()
        for key in ra:
            if key != "rows" and ra[key] != rb[key]:
                problems.append(f"image {i}: {key} {ra[key]} != {rb[key]}")
        if [(r.valid, r.reason, r.hypothesis) for r in a.rows] != [(r.valid, r.reason, r.hypothesis) for r in b.rows]:
            problems.append(f"image {i}: row validity/reason/hypothesis differ")
            continue
        for ya, yb in zip(a.rows, b.rows):
            for u, v in ((ya.a, yb.a), (ya.b, yb.b)):
                if not (np.isnan(u) and np.isnan(v)) and not abs(u - v) <= tol:
                    problems.append(f"image {i}: row {u} vs {v}")
            # the row's x over the image height, in px
            ys = np.arange(a.height, dtype=np.float64)
            if not np.isnan(ya.a) and np.abs(ya.x_at(ys) - yb.x_at(ys)).max() > tol:
                problems.append(f"image {i}: row x differs by more than {tol} px")
    if len(ref) != len(got):
        problems.append(f"{len(ref)} vs {len(got)} results")
    return problems


@pytest.fixture(scope="module")
def scatter_free_path(tmp_path_factory) -> Path:
    """The scatter-free detector without control flow (the TensorRT-parsable form), at a
    small working size (the op list does not depend on it)."""
    return _exported(SMALL, 1, tmp_path_factory.mktemp("onnx-sf"), 90, 160, control_flow=False, scatter_free=True)


# ------------------------------------------------------------------------------------------
# heavy: the scatter-free, If-free export adds about 50 s to a cold CI run (exports are cached by
# source hash, so every change to torchrow pays them); the onnxruntime form below stays
@pytest.mark.heavy
def test_op_list_of_the_scatter_free_form(scatter_free_path: Path):
    import onnx

    ops = op_counts(onnx.load(str(scatter_free_path)))
    assert not [op for op in ops if op in FORBIDDEN_OPS], ops
    assert set(ops) <= ALLOWED_OPS, f"ops outside the TensorRT whitelist: {set(ops) - ALLOWED_OPS}"
    assert ops["CumSum"] > 0 and ops["TopK"] > 0  # the vote and the band points


@pytest.mark.heavy
def test_scatter_free_form_equals_torch(scatter_free_path: Path):
    x = torch.from_numpy(np.stack([sequence(FieldSpec.at_size(160, 90, n_rows=5, seed=3), 1)[0].image]))
    x = x.permute(0, 3, 1, 2).contiguous()
    ref = CropRowDetector(SMALL.replace(image_width=160))(x).results()
    assert not _same(ref, OnnxDetector(scatter_free_path)(x).results())


def test_default_form_votes_by_scatter_add_and_exits_early(model_path: Path):
    """The onnxruntime form: one scatter-add vote updated by bands, the line search one
    ``Loop`` (stored once, stopping when every image is done), vote chunks in ``If`` nodes."""
    import onnx

    from torchrow.functional.vanishing import max_steps

    ops = op_counts(onnx.load(str(model_path)))
    # the search's body once: an unrolled search holds a peak (ArgMax) per step
    assert ops["ScatterElements_reduction"] > 0 and ops["Loop"] == 1 and ops["If"] > 0, ops
    assert ops["ArgMax"] < max_steps(SMALL), ops
    assert not {"NonZero", "Unique", "Scan"} & set(ops), ops


def test_share_initializers_keeps_one_copy_and_the_results():
    """Equal tables in the main graph and in both branches of an ``If`` (as constant folding
    leaves them) become one main-graph initializer that the branches read as an outer value;
    a branch's own different table and a nested body's stay; onnxruntime gives the same results
    before and after."""
    import onnx
    import onnxruntime as ort
    from onnx import TensorProto, helper, numpy_helper

    from torchrow.onnx.passes import drop_unused_initializers, share_initializers

    table = np.arange(300, dtype=np.float32)
    x = helper.make_tensor_value_info("x", TensorProto.FLOAT, [300])
    y = helper.make_tensor_value_info("y", TensorProto.FLOAT, [300])

    def init(name, arr):
        return numpy_helper.from_array(arr, name)

    def inner(tag):  # a nested body reading the outer table and its own
        return helper.make_graph(
            [helper.make_node("Add", ["x", "t_else"], [f"{tag}_a"]), helper.make_node("Add", [f"{tag}_a", f"{tag}_t"],
                                                                                  [f"{tag}_y"])],
            tag, [], [helper.make_tensor_value_info(f"{tag}_y", TensorProto.FLOAT, [300])], [init(f"{tag}_t", table * 3)])
    then = helper.make_graph([helper.make_node("Add", ["x", "t_then"], ["y_then"]),
                              helper.make_node("Add", ["y_then", "t_own"], ["y_then2"])],
                             "then", [], [helper.make_tensor_value_info("y_then2", TensorProto.FLOAT, [300])],
                             [init("t_then", table), init("t_own", table * 2)])
    other = helper.make_graph([helper.make_node("Mul", ["x", "t_else"], ["y_else0"]),
                               helper.make_node("If", ["c"], ["y_inner"], then_branch=inner("in1"), else_branch=inner("in2")),
                               helper.make_node("Add", ["y_else0", "y_inner"], ["y_else"])],
                              "else", [], [helper.make_tensor_value_info("y_else", TensorProto.FLOAT, [300])],
                              [init("t_else", table)])
    graph = helper.make_graph([helper.make_node("If", ["c"], ["z"], then_branch=then, else_branch=other),
                               helper.make_node("Sub", ["z", "t_main"], ["y"])],
                              "main", [x, helper.make_tensor_value_info("c", TensorProto.BOOL, [])], [y],
                              [init("t_main", table)])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    onnx.checker.check_model(model)

    def run(m, c):
        sess = ort.InferenceSession(m.SerializeToString(), providers=["CPUExecutionProvider"])
        return sess.run(None, {"x": np.linspace(-1, 1, 300, dtype=np.float32), "c": np.array(c)})[0]

    want = [run(model, c) for c in (True, False)]
    shared = drop_unused_initializers(share_initializers(onnx.ModelProto.FromString(model.SerializeToString())))
    onnx.checker.check_model(shared)
    g = shared.graph
    branches = {a.name: a.g for a in g.node[0].attribute}
    nested = [a.g for a in branches["else_branch"].node[1].attribute]
    main_names = [i.name for i in g.initializer]
    assert len(main_names) == 2 and main_names[0] == "t_main"
    assert np.array_equal(numpy_helper.to_array(g.initializer[1]), table * 3)
    assert [i.name for i in branches["then_branch"].initializer] == ["t_own"]  # its own values: stays
    assert not branches["else_branch"].initializer and branches["else_branch"].node[0].input[1] == "t_main"
    assert [(len(n.initializer), n.node[0].input[1], n.node[1].input[1]) for n in nested] == [
        (0, "t_main", main_names[1])] * 2
    for c, w in zip((True, False), want):
        assert np.array_equal(run(shared, c), w)


def test_ort_native_small_integer_ops_run_and_agree_with_int32():
    """Every (op, type) that legalize leaves narrow for onnxruntime has a CPU kernel in the
    installed onnxruntime, and gives the int32 computation's values (cast back) on edge
    values of the type."""
    import onnxruntime as ort
    from onnx import TensorProto, helper

    from torchrow.onnx.passes import ORT_NATIVE

    unary = {"Abs", "BitwiseNot", "Neg", "ReduceMax", "ReduceMin", "ArgMax", "Clip"}
    compare = {"Equal", "Greater", "GreaterOrEqual", "Less", "LessOrEqual"}
    for tname, ops in ORT_NATIVE.items():
        dt = getattr(TensorProto, tname)
        npt = helper.tensor_dtype_to_np_dtype(dt)
        info = np.iinfo(npt)
        a = np.array([info.min, info.min + 1, -1 if info.min < 0 else 2, 0, 1, 7, info.max - 1, info.max], dtype=npt)
        b = a[::-1].copy()
        for op in sorted(ops):
            n_in = 1 if op in unary else (3 if op == "Where" else 2)
            out_t = TensorProto.BOOL if op in compare else (TensorProto.INT64 if op == "ArgMax" else None)

            def run(t, arrays, op=op, out_t=out_t):
                names = [f"x{i}" for i in range(len(arrays))]
                ins = [helper.make_tensor_value_info(n, TensorProto.BOOL if op == "Where" and i == 0 else t, [8])
                       for i, n in enumerate(names)]
                g = helper.make_graph([helper.make_node(op, names, ["y"])], "g", ins,
                                      [helper.make_tensor_value_info("y", out_t or t, None)])
                m = helper.make_model(g, opset_imports=[helper.make_opsetid("", 18)])
                m.ir_version = 9
                sess = ort.InferenceSession(m.SerializeToString(), providers=["CPUExecutionProvider"])
                return sess.run(None, dict(zip(names, arrays)))[0]

            args = {1: [a], 2: [a, b], 3: [a > b, a, b]}[n_in]
            got = run(dt, args)
            wide = run(TensorProto.INT32, [x if x.dtype == bool else x.astype(np.int32) for x in args])
            if out_t is None:
                wide = wide.astype(npt)  # the cast back legalize would have made (wraps)
            assert np.array_equal(got, wide), (tname, op, got, wide)


def test_model_metadata(model_path: Path):
    info = model_info(model_path)
    assert (info["height"], info["width"], info["batch"], info["opset"]) == (240, 320, BATCH, 18)
    assert info["params"] == SMALL
    assert "dynamo" in info["exporter"]


def _synthetic_batch() -> torch.Tensor:
    """Adversarial images: all soil (no vegetation), all green (bushy), a sky band, noise."""
    rng = np.random.default_rng(0)
    imgs = np.zeros((5, 240, 320, 3), np.uint8)
    imgs[0] = (120, 90, 60)  # soil only
    imgs[1] = (40, 160, 40)  # one dense green field: bushy
    imgs[1, ::7] = (120, 90, 60)
    imgs[2] = (120, 90, 60)  # sky on top, green rows below
    imgs[2, :60] = (200, 220, 250)
    for x0 in range(20, 320, 60):
        for y in range(60, 240):
            x = int(x0 + (y - 60) * (160 - x0) / 400)
            imgs[2, y, max(0, x - 3):x + 3] = (40, 160, 40)
    imgs[3] = rng.integers(0, 256, (240, 320, 3), dtype=np.uint8)
    imgs[4] = imgs[2, :, ::-1]
    return torch.from_numpy(imgs).permute(0, 3, 1, 2).contiguous()


def test_parity_synthetic(runner: OnnxDetector):
    x = _synthetic_batch()
    ref = CropRowDetector(SMALL)(x).results()
    got = runner(x).results()
    assert not _same(ref, got)
    assert {r.status for r in ref} >= {"no_vegetation"}
    assert any(r.bushy for r in ref)


@pytest.mark.data
def test_parity_crbd_sample(runner: OnnxDetector, crbd_dir: Path):
    from torchrow.evaluation.datasets import CRBD

    ds = CRBD(crbd_dir)
    idx = [0, 57, 130, 200, 280]  # odd count: the last batch is padded
    x = torch.from_numpy(np.stack([ds.image(i) for i in idx])).permute(0, 3, 1, 2).contiguous()
    ref = CropRowDetector(SMALL)(x).results()
    got = runner(x).results()
    assert not _same(ref, got)


def test_ort_optimized_copy_is_cached_reused_and_equal(model_path: Path, tmp_path: Path, monkeypatch):
    """The session opens onnxruntime's pre-optimised copy: written once, reused after, the
    same results as the original opened with basic optimisations; disabled by
    TORCHROW_ORT_CACHE=0; an unwritable cache folder falls back to the original."""
    from torchrow.onnx import runtime as export

    monkeypatch.setenv("TORCHROW_CACHE", str(tmp_path / "cache"))
    x = _synthetic_batch()
    plain = OnnxDetector(model_path, cache=False)(x).results()
    first = OnnxDetector(model_path)
    files = list((tmp_path / "cache" / "ort").glob("*.onnx"))
    assert len(files) == 1, files
    inode = files[0].stat().st_ino
    again = OnnxDetector(model_path)
    assert export.ort_optimized(model_path) == files[0] and files[0].stat().st_ino == inode  # reused
    assert not _same(plain, first(x).results()) and not _same(plain, again(x).results())
    monkeypatch.setenv("TORCHROW_ORT_CACHE", "0")
    assert export.ort_optimized(model_path) is None
    monkeypatch.setenv("TORCHROW_ORT_CACHE", "1")
    (tmp_path / "file").write_text("not a folder")
    monkeypatch.setenv("TORCHROW_CACHE", str(tmp_path / "file"))
    assert export.ort_optimized(model_path) is None
    assert not _same(plain, OnnxDetector(model_path)(x).results())


def test_veg_color_override(runner: OnnxDetector):
    x = _synthetic_batch()[2:4]
    color = torch.tensor([40, 160, 40], dtype=torch.uint8)
    ref = CropRowDetector(SMALL)(x, veg_color=color).results()
    assert not _same(ref, runner(x, veg_color=color).results())


def test_wrong_size_is_a_clear_error(runner: OnnxDetector):
    with pytest.raises(ValueError, match="takes 320x240 images, got 160x120"):
        runner(torch.zeros((1, 3, 120, 160), dtype=torch.uint8))


def test_missing_model_is_a_clear_error(tmp_path: Path):
    with pytest.raises(FileNotFoundError, match="ONNX model not found"):
        OnnxDetector(tmp_path / "nope.onnx")


def test_export_argument_errors(tmp_path: Path):
    with pytest.raises(ValueError, match="batch must be an integer >= 1"):
        to_onnx(tmp_path / "m.onnx", batch=0)
    with pytest.raises(ValueError, match="opset must be an integer >= 18"):
        to_onnx(tmp_path / "m.onnx", opset=17)
    with pytest.raises(FileNotFoundError, match="output folder does not exist"):
        to_onnx(tmp_path / "missing" / "m.onnx")


@pytest.mark.parametrize(("argv", "words"), [
    (["--batch", "100000"], "batch of a detector export must be <= 256"),
    (["--tracker", "--height", "281", "--batch", "1000"], "batch of a tracker export must be <= 64"),
    (["--width", "5000"], "--width: Params.image_width"),
    (["--tracker", "--width", "5000", "--height", "10"], "--width: Params.video_width"),
    (["--height", "200000"], "320x200000 working image has 64000000 pixels, more than max_pixels"),
    (["--height", "10000000"], "height of a detector export must be <= 524288"),
])
def test_export_sizes_are_bounded_before_tracing(tmp_path: Path, capsys, argv, words):
    """Issue 26: absurd export sizes are one line (exit 2) at once, not a traceback or
    gigabytes of example inputs."""
    from torchrow.apps.cli import main

    assert main(["export", "onnx", "--out", str(tmp_path / "m.onnx"), "-q", *argv]) == 2
    err = capsys.readouterr().err
    assert words in err and err.count("\n") == 1, err
    assert not (tmp_path / "m.onnx").exists()


# --- CLI -------------------------------------------------------------------------------------
def _write_images(folder: Path, batch: torch.Tensor) -> None:
    import cv2

    folder.mkdir()
    for i, im in enumerate(batch.permute(0, 2, 3, 1).numpy()):
        cv2.imwrite(str(folder / f"im{i}.png"), im[..., ::-1])


def _records(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines()]


def test_cli_detect_onnx_equals_tensor(model_path: Path, tmp_path: Path):
    _write_images(tmp_path / "imgs", _synthetic_batch())
    a, b = tmp_path / "tensor.jsonl", tmp_path / "onnx.jsonl"
    params = [f"--param=n_rows={SMALL.n_rows}", f"--param=max_outliers={SMALL.max_outliers}"]
    assert main(["detect", str(tmp_path / "imgs"), "--out", str(a), "-q", *params]) == 0
    assert main(["detect", str(tmp_path / "imgs"), "--out", str(b), "-q", "--impl", "onnx",
                 "--model", str(model_path)]) == 0
    ra, rb = _records(a), _records(b)
    assert [r["name"] for r in ra] == [r["name"] for r in rb]
    for x, y in zip(ra, rb):
        assert {k: v for k, v in x.items() if k != "rows"} == {k: v for k, v in y.items() if k != "rows"}
        assert [(r["valid"], r["reason"]) for r in x["rows"]] == [(r["valid"], r["reason"]) for r in y["rows"]]
        for r, s in zip(x["rows"], y["rows"]):
            for key in ("a", "b"):
                assert (r[key] is None and s[key] is None) or abs(r[key] - s[key]) <= 1e-4


def test_runner_onnx_workers_keep_order_and_records(model_path: Path):
    from torchrow.core.io import ImageError
    from torchrow.engines.runner import run

    imgs = list(_synthetic_batch().permute(0, 2, 3, 1).numpy())

    def unreadable():
        raise ImageError("broken file")

    odd = np.zeros((100, 160, 3), np.uint8)  # not the model's working size: an error record
    arrays = [imgs[0], imgs[1], None, imgs[2], odd, imgs[3], imgs[4], imgs[0], imgs[2]]
    items = [(f"im{i}", unreadable if a is None else (lambda a=a: a)) for i, a in enumerate(arrays)]
    want = [(i, r.to_record()) for i, _, r, _ in run(items, impl="onnx", model=str(model_path), progress=False,
                                                        workers=1)]
    assert [i for i, _ in want] == list(range(len(items)))
    assert want[2][1]["status"] == "error" and "broken file" in want[2][1]["error"]
    assert want[4][1]["status"] == "error" and "takes 320x240" in want[4][1]["error"]
    ref = CropRowDetector(SMALL)(torch.from_numpy(np.stack(imgs)).permute(0, 3, 1, 2).contiguous()).results()
    assert _same([ref[0], ref[1], ref[2], ref[3]], [OnnxDetector(model_path).detect([imgs[k]]).results()[0]
                                                     for k in range(4)]) == []
    for workers, window in ((2, None), (3, None), (3, 2)):
        got = list(run(items, impl="onnx", model=str(model_path), progress=False, workers=workers, window=window))
        assert [i for i, *_ in got] == list(range(len(items)))
        if window is None:  # the same batches as with one worker: the same bits
            assert [(i, r.to_record()) for i, _, r, _ in got] == want, workers
        else:  # other batches (the window flushes part-filled ones): equal by the spec's tolerance
            for (_, x), (_, _, r, _) in zip(want, got):
                y = r.to_record()
                assert {k: v for k, v in x.items() if k != "rows"} == {k: v for k, v in y.items() if k != "rows"}
                assert [(q["valid"], q["reason"]) for q in x["rows"]] == [(q["valid"], q["reason"]) for q in y["rows"]]
                for q, u in zip(x["rows"], y["rows"]):
                    assert all(abs(q[k] - u[k]) <= 1e-9 for k in ("a", "b") if q[k] is not None)
    with pytest.raises(ValueError, match="workers is only used with impl='onnx'"):
        list(run(items, impl="tensor", workers=2))
    with pytest.raises(ValueError, match="workers must be >= 1"):
        list(run(items, impl="onnx", model=str(model_path), workers=0))


def test_cli_onnx_errors(model_path: Path, tmp_path: Path, capsys):
    _write_images(tmp_path / "imgs", _synthetic_batch()[:1])
    out = str(tmp_path / "o.jsonl")
    assert main(["detect", str(tmp_path / "imgs"), "--out", out, "--impl", "onnx"]) == 2
    assert "--impl onnx needs --model" in capsys.readouterr().err
    assert main(["detect", str(tmp_path / "imgs"), "--out", out, "--impl", "onnx", "--model",
                 str(tmp_path / "none.onnx")]) == 2
    assert "ONNX model not found" in capsys.readouterr().err
    small = tmp_path / "small"
    small.mkdir()
    import cv2

    cv2.imwrite(str(small / "a.png"), np.zeros((100, 640, 3), np.uint8))
    assert main(["detect", str(small), "--out", out, "--impl", "onnx", "--model", str(model_path)]) == 2
    err = capsys.readouterr().err
    assert "takes 320x240 images" in err and err.count("\n") == 1
    assert main(["detect", str(tmp_path / "imgs"), "--out", out, "--model", str(model_path)]) == 2
    assert "--model is only used with --impl onnx" in capsys.readouterr().err


# --- slow: the default-parameter model on all CRBD images ------------------------------------
@pytest.mark.heavy
@pytest.mark.data
def test_parity_all_crbd_default_params(crbd_dir: Path, tmp_path_factory):
    from torchrow.evaluation.datasets import CRBD

    path = _exported(Params(), 4, tmp_path_factory.mktemp("onnx-full"))
    det = OnnxDetector(path)
    ds = CRBD(crbd_dir)
    problems = []
    for s in range(0, len(ds), 32):
        idx = list(range(s, min(len(ds), s + 32)))
        x = torch.from_numpy(np.stack([ds.image(i) for i in idx])).permute(0, 3, 1, 2).contiguous()
        problems += _same(CropRowDetector()(x).results(), det(x).results())
    assert not problems, problems[:10]


@pytest.mark.heavy
def test_lab_box_decisions_exhaustive():
    """All 2**24 colours through the graph's LAB in onnxruntime: no box decision of any
    vegetation colour can differ from the shared table's, for image mode's k and every
    adaptive k of video mode (about 30 s)."""
    from torchrow.onnx.checks import check_lab

    p = Params()
    res = check_lab(k=[p.veg_tol, *range(p.video_k_min, p.video_k_max + 1)])
    assert res["flippable"] == 0, res
    assert res["max_abs_diff"] < 1e-12, res  # ulps, not a float32 constant (see the next test)


def test_python_float_constants_stay_float64():
    """Without float64_python_constants the exporter rounds ``x * 0.412453`` and ``x > 1.2``'s
    constants to float32 (the graph's LAB moved by up to 7e-6); with it the graph equals torch."""
    import warnings

    import onnxruntime as ort

    from torchrow.onnx.shims import float64_python_constants

    class M(torch.nn.Module):
        def forward(self, x):
            return x * 0.412453, (x * 0.5 + 4.0 / 29.0) < 1.2 * x

    x = torch.tensor([1.0, 3.0, 1.2, 0.13793103448275862, 1.2000000476837158], dtype=torch.float64)
    results = []
    for fix in (False, True):
        with warnings.catch_warnings(), torch.no_grad():
            warnings.simplefilter("ignore")
            ep = torch.export.export(M(), (x,), strict=False)
            with float64_python_constants() if fix else contextlib.nullcontext():
                prog = torch.onnx.export(ep, dynamo=True, opset_version=18, verbose=False, optimize=False)
        sess = ort.InferenceSession(prog.model_proto.SerializeToString(), providers=["CPUExecutionProvider"])
        got = sess.run(None, {sess.get_inputs()[0].name: x.numpy()})
        results.append(all(np.array_equal(g, r.numpy()) for g, r in zip(got, M()(x))))
    assert results == [False, True]  # the first documents the exporter's behaviour this works around
