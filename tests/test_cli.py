"""The command line end to end: mixed folders, bad inputs, records, eval/score on CRBD."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from torchrow.apps.cli import main
from torchrow.core.params import Params
from torchrow.evaluation.synthetic import FieldSpec, render

RECORD_KEYS = {"name", "status", "sky", "veg_color", "k", "bushy", "n_rows", "hough", "outliers", "vp",
               "rows", "width", "height"}


@pytest.fixture
def mixed_folder(tmp_path: Path) -> Path:
    """Two synthetic fields (.png and .JPG), a wide one, grey, RGBA, 16-bit, garbage, truncated, empty."""
    d = tmp_path / "in"
    d.mkdir()
    f1 = render(FieldSpec(seed=1))
    f2 = render(FieldSpec(seed=2, width=640, height=480))
    cv2.imwrite(str(d / "a_field.png"), cv2.cvtColor(f1.image, cv2.COLOR_RGB2BGR))
    cv2.imwrite(str(d / "b_field.JPG"), cv2.cvtColor(f2.image, cv2.COLOR_RGB2BGR))
    cv2.imwrite(str(d / "c_grey.png"), cv2.cvtColor(f1.image, cv2.COLOR_RGB2GRAY))
    cv2.imwrite(str(d / "d_rgba.png"), cv2.cvtColor(f1.image, cv2.COLOR_RGB2BGRA))
    cv2.imwrite(str(d / "e_16bit.png"), cv2.cvtColor(f1.image, cv2.COLOR_RGB2BGR).astype(np.uint16) * 257)
    (d / "f_garbage.jpg").write_bytes(b"not an image at all")
    jpg = cv2.imencode(".jpg", f1.image)[1].tobytes()
    (d / "g_truncated.jpg").write_bytes(jpg[:200])
    (d / "h_empty.png").write_bytes(b"")
    (d / "notes.txt").write_text("ignored: not an image extension")
    return d


def _records(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines()]


def test_detect_mixed_folder(mixed_folder: Path, tmp_path: Path, capsys) -> None:
    out = tmp_path / "res.jsonl"
    ann = tmp_path / "ann"
    assert main(["detect", str(mixed_folder), "--out", str(out), "--annotate", str(ann), "-q"]) == 0
    recs = {r["name"]: r for r in _records(out)}
    assert sorted(recs) == sorted(p.name for p in mixed_folder.iterdir() if p.suffix != ".txt")
    for r in recs.values():
        assert RECORD_KEYS <= set(r)
    for bad in ("f_garbage.jpg", "g_truncated.jpg", "h_empty.png"):
        assert recs[bad]["status"] == "error" and recs[bad]["error"]
    good = recs["a_field.png"]
    assert good["status"] in ("ok", "invalid") and good["width"] == 320 and good["height"] == 240
    assert any(row["valid"] for row in good["rows"])
    # the 640x480 field is resized to the working width
    assert (recs["b_field.JPG"]["width"], recs["b_field.JPG"]["height"]) == (320, 240)
    # conversion rule: RGBA and 16-bit decode to the same 8-bit RGB as the PNG
    for conv in ("d_rgba.png", "e_16bit.png"):
        assert recs[conv]["rows"] == good["rows"] and recs[conv]["hough"] == good["hough"]
    assert recs["c_grey.png"]["status"] in ("ok", "invalid", "no_vp", "no_vegetation")
    assert sorted(p.name for p in ann.iterdir()) == sorted(
        Path(n).stem + ".png" for n, r in recs.items() if r["status"] != "error")
    assert "image(s)" in capsys.readouterr().err


def test_record_row_geometry(tmp_path: Path) -> None:
    """Rows in records are x = a*y + b in working pixels: valid rows lie on the true rows."""
    field = render(FieldSpec(seed=3))
    p = tmp_path / "f.png"
    cv2.imwrite(str(p), cv2.cvtColor(field.image, cv2.COLOR_RGB2BGR))
    out = tmp_path / "r.jsonl"
    assert main(["detect", str(p), "--out", str(out), "-q"]) == 0
    rec = _records(out)[0]
    h = rec["height"]
    true_bottom = [a * (h - 1) + b for a, b in field.rows]
    for row in rec["rows"]:
        if row["valid"]:
            x = row["a"] * (h - 1) + row["b"]
            assert min(abs(x - t) for t in true_bottom) < 6.0


@pytest.mark.parametrize(("argv", "msg"), [
    (["detect", "/no/such/path.jpg", "--out", "x.jsonl"], "no such file or folder"),
    (["detect", ".", "--out", "/no/such/dir/x.jsonl"], None),
    (["eval", "--data", "/no/such/crbd"], "crbd"),
    (["score", "--data", "/no/such/crbd", "--results", "."], "crbd"),
    (["detect", "--param", "n_rows=0", ".", "--out", "x.jsonl"], "n_rows"),
    (["detect", "--param", "bogus=1", ".", "--out", "x.jsonl"], "bogus"),
])
def test_bad_arguments_one_line_error(argv, msg, tmp_path: Path, monkeypatch, capsys) -> None:
    monkeypatch.chdir(tmp_path)
    (tmp_path / "img.png").write_bytes(cv2.imencode(".png", np.zeros((4, 4, 3), np.uint8))[1].tobytes())
    rc = main(argv)
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2
    assert len(err) == 1 and err[0].startswith("torchrow: error:")
    if msg:
        assert msg.lower() in err[0].lower()


def test_empty_folder_is_an_error(tmp_path: Path, capsys) -> None:
    assert main(["detect", str(tmp_path), "--out", str(tmp_path / "x.jsonl")]) == 2
    assert "no images" in capsys.readouterr().err


def test_demo_runs_without_data(tmp_path: Path, capsys) -> None:
    out = tmp_path / "demo.png"
    assert main(["demo", "--out", str(out)]) == 0
    img = cv2.imread(str(out))
    assert img is not None and img.shape[0] >= 240
    text = capsys.readouterr().out
    assert "CRDA" in text and "valid rows" in text
    score = float(text.split("CRDA (sigma 0.1)")[1].split()[0])
    assert score > 0.5  # the demo field is easy: the detector must find its rows


def test_python_dash_m_entry_point(tmp_path: Path) -> None:
    r = subprocess.run([sys.executable, "-m", "torchrow", "--version"], capture_output=True, text=True)
    assert r.returncode == 0 and r.stdout.startswith("torchrow ")


@pytest.mark.data
def test_eval_and_score_on_crbd(crbd_dir: Path, tmp_path: Path, capsys) -> None:
    out = tmp_path / "eval"
    assert main(["eval", "--data", str(crbd_dir), "--every", "40", "--out", str(out), "-q", "--impl", "reference"]) == 0
    text = capsys.readouterr().out
    assert "straight" in text and "curved" in text
    for f in ("scores.csv", "detections.jsonl", "summary.json", "crda_histogram.png"):
        assert (out / f).is_file()
    recs = _records(out / "detections.jsonl")
    assert len(recs) == len(range(0, 281, 40))
    summary = json.loads((out / "summary.json").read_text())
    assert summary["all"]["crda_01"]["n"] == len(recs)
    assert main(["score", "--data", str(crbd_dir), "--results", str(crbd_dir / "TMGEM results"), "-q"]) == 0
    text = capsys.readouterr().out
    assert "sigma 0.1: mean 0.746  median 0.767" in text


def test_detect_tensor_and_reference_agree(mixed_folder: Path, tmp_path: Path) -> None:
    """--impl tensor (batched, several sizes in one run) writes the reference's records."""
    outs = {}
    for impl, extra in (("reference", []), ("tensor", ["--batch-size", "2"])):
        out = tmp_path / f"{impl}.jsonl"
        assert main(["detect", str(mixed_folder), "--out", str(out), "-q", "--impl", impl, *extra]) == 0
        outs[impl] = _records(out)
    assert [r["name"] for r in outs["reference"]] == [r["name"] for r in outs["tensor"]]
    for a, b in zip(outs["reference"], outs["tensor"]):
        for key in RECORD_KEYS - {"rows", "vp"}:
            assert a[key] == b[key], (a["name"], key)
        assert [(r["valid"], r["reason"]) for r in a["rows"]] == [(r["valid"], r["reason"]) for r in b["rows"]]
        for ra, rb in zip(a["rows"], b["rows"]):
            assert (ra["b"] is None and rb["b"] is None) or abs(ra["b"] - rb["b"]) < 1e-6


def test_unknown_device_is_a_one_line_error(tmp_path: Path, capsys) -> None:
    assert main(["detect", str(tmp_path), "--out", str(tmp_path / "x.jsonl"), "--device", "warp9"]) == 2
    assert capsys.readouterr().err.startswith("torchrow: error: bad --device")


@pytest.mark.data
def test_eval_tensor_equals_reference_scores(crbd_dir: Path, tmp_path: Path) -> None:
    import csv

    rows = {}
    for impl in ("reference", "tensor"):
        out = tmp_path / impl
        assert main(["eval", "--data", str(crbd_dir), "--every", "25", "--out", str(out), "-q",
                     "--impl", impl]) == 0
        rows[impl] = [{k: v for k, v in r.items() if k != "seconds"}
                      for r in csv.DictReader(open(out / "scores.csv"))]
    assert rows["reference"] == rows["tensor"]


def test_forward_flag_applies_the_forward_camera_setting_under_param() -> None:
    import argparse

    from torchrow.apps.commands.shared import CLIError, parse_params, with_mode
    from torchrow.core.params import FORWARD_CAMERA

    def args(**kw):
        base = {"mode": None, "forward": True, "param": None, "impl": "tensor", "command": "video"}
        return argparse.Namespace(**{**base, **kw})

    p = with_mode(parse_params(None), args())
    assert p.mode == "improved" and all(getattr(p, k) == v for k, v in FORWARD_CAMERA.items())
    items = ["lattice_vp_origin=top", "lattice_max_spacing=200"]
    q = with_mode(parse_params(items), args(param=items))  # --param wins over --forward
    assert (q.lattice_vp_origin, q.lattice_max_spacing, q.lattice_min_spacing) == ("top", 200, 16)
    with pytest.raises(CLIError, match="leave out --mode faithful"):
        with_mode(parse_params(None), args(mode="faithful"))
    assert with_mode(parse_params(None), args(forward=None)).mode == "faithful"
    assert with_mode(parse_params(None), args(forward=False)) == Params(mode="improved")  # --no-forward


@pytest.mark.parametrize(("argv", "forward"), [
    (["video", "F", "--out", "o.jsonl", "--mode", "improved"], True),  # the lattice tracker: a robot's camera
    (["video", "F", "--out", "o.jsonl", "--param", "mode=improved"], True),
    (["video", "F", "--out", "o.jsonl", "--mode", "improved", "--no-forward"], False),
    (["export", "onnx", "--out", "t.onnx", "--tracker", "--mode", "improved"], True),
    (["detect", "F", "--out", "o.jsonl", "--mode", "improved"], False),  # a camera looking down, as CRBD's
    (["eval", "--data", "D", "--out", "O", "--mode", "improved"], False),
    (["detect", "F", "--out", "o.jsonl", "--forward"], True),
])
def test_the_tracker_takes_the_forward_camera_setting_unless_told_otherwise(argv: list[str], forward: bool) -> None:
    from torchrow.apps.cli import build_parser
    from torchrow.apps.commands.shared import parse_params, with_mode
    from torchrow.core.params import FORWARD_CAMERA

    args = build_parser().parse_args(argv)
    p = with_mode(parse_params(args.param), args)
    assert p.mode == "improved"
    assert all(getattr(p, k) == v for k, v in FORWARD_CAMERA.items()) is forward
    assert p == (Params(mode="improved", **FORWARD_CAMERA) if forward else Params(mode="improved"))


def test_setting_hint_names_forward_only_where_the_default_setting_failed_most_images() -> None:
    from torchrow.apps.commands.shared import setting_hint
    from torchrow.core.params import FORWARD_CAMERA

    improved = Params(mode="improved")
    assert "--forward" in setting_hint(improved, {"weak": 3, "ok": 2})
    assert setting_hint(improved, {"weak": 2, "ok": 2}) is None
    assert setting_hint(improved, {}) is None
    assert setting_hint(Params(), {"weak": 5}) is None  # faithful
    assert setting_hint(Params(mode="improved", **FORWARD_CAMERA), {"weak": 5}) is None
    assert setting_hint(Params(mode="improved", lattice_vp_origin="sky"), {"weak": 5}) is None
