"""Bounded memory and one input contract for both paths (issue 11, reproducers 4 and 8-10).

The memory test runs ``torchrow detect`` in a subprocess under an address-space limit
(``RLIMIT_AS`` = 3 GiB), so a regression fails the test instead of taking the machine down.
"""

from __future__ import annotations

import json
import os
import resource
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

import torchrow
from torchrow import CropRowDetector, Params, Tracker
from torchrow import reference as ref
from torchrow.core.io import ImageError, check_working_size, load_image
from torchrow.engines.runner import run
from torchrow.evaluation.synthetic import FieldSpec, render

GIB = 1 << 30


def _limited(argv: list[str], limit: int = 3 * GIB) -> subprocess.CompletedProcess:
    def cap() -> None:
        resource.setrlimit(resource.RLIMIT_AS, (limit, limit))

    return subprocess.run([sys.executable, "-m", "torchrow", *argv], preexec_fn=cap, capture_output=True,
                          text=True, timeout=600)


@pytest.fixture(scope="module")
def shapes(tmp_path_factory) -> Path:
    """The issue's 7x900 and 4x3000 PNGs, a normal field, and a tall field just inside the bound."""
    d = tmp_path_factory.mktemp("shapes")
    rng = np.random.default_rng(0)
    cv2.imwrite(str(d / "a_7x900.png"), rng.integers(0, 256, (900, 7, 3), dtype=np.uint8))
    cv2.imwrite(str(d / "b_4x3000.png"), rng.integers(0, 256, (3000, 4, 3), dtype=np.uint8))
    field = render(FieldSpec(seed=1)).image
    cv2.imwrite(str(d / "c_field.png"), cv2.cvtColor(field, cv2.COLOR_RGB2BGR))
    h = Params().max_pixels // 320  # 1638 rows at width 320: the largest allowed working size
    tall = render(FieldSpec(seed=2, width=320, height=h)).image
    cv2.imwrite(str(d / "d_tall.png"), cv2.cvtColor(tall, cv2.COLOR_RGB2BGR))
    return d


@pytest.mark.parametrize("impl", ["tensor", "reference"])
def test_detect_any_shape_within_3_gib(shapes: Path, tmp_path: Path, impl: str) -> None:
    """Reproducer 4: 320x41142 and 320x240000 working sizes asked for 8.8 and 51.5 GiB; the
    kernel killed the run and its JSONL was empty. Now: error records naming the rule, the
    other images done, all under a 3 GiB address-space limit."""
    out = tmp_path / "r.jsonl"
    r = _limited(["detect", str(shapes), "--out", str(out), "-q", "--impl", impl, "--batch-size", "2"])
    assert r.returncode == 0, r.stderr[-2000:]
    recs = {x["name"]: x for x in map(json.loads, out.read_text().splitlines())}
    for bad, h in (("a_7x900.png", 41142), ("b_4x3000.png", 240000)):
        assert recs[bad]["status"] == "error"
        assert f"working size 320x{h}" in recs[bad]["error"] and "max_pixels" in recs[bad]["error"]
    assert recs["c_field.png"]["status"] in ("ok", "invalid")
    assert recs["d_tall.png"]["status"] != "error" and recs["d_tall.png"]["height"] == 1638


def test_large_image_width_is_an_error_record_not_4_gib(shapes: Path, tmp_path: Path) -> None:
    """Reproducer 4: `--param image_width=4000` needed 4 GiB."""
    out = tmp_path / "r.jsonl"
    r = _limited(["detect", str(shapes / "c_field.png"), "--out", str(out), "-q", "--param", "image_width=4000"])
    assert r.returncode == 0, r.stderr[-2000:]
    (rec,) = map(json.loads, out.read_text().splitlines())
    assert rec["status"] == "error" and "4000x3000" in rec["error"] and "max_pixels" in rec["error"]


def test_working_size_bound_same_rule_in_both_paths() -> None:
    p = Params(max_pixels=320 * 300)
    tall = render(FieldSpec(seed=3, width=320, height=320)).image  # 102,400 px > 96,000
    with pytest.raises(ImageError, match="max_pixels") as e_ref:
        ref.detect(tall, p)
    det = CropRowDetector(p)
    x = torch.from_numpy(tall).permute(2, 0, 1)[None].contiguous()
    with pytest.raises(ImageError, match="max_pixels") as e_ten:
        det(x)
    assert str(e_ref.value) == str(e_ten.value)
    with pytest.raises(ImageError, match="max_pixels"):
        Tracker(p.replace(video_width=320)).step([tall])
    with pytest.raises(ImageError, match="max_pixels"):
        ref.Tracker(p.replace(video_width=320)).step(tall)
    # through the runner both paths write the same record
    items = [("tall", lambda: tall)]
    recs = [next(iter(run(items, impl, p, progress=False)))[2].to_record() for impl in ("tensor", "reference")]
    assert recs[0] == recs[1] and recs[0]["status"] == "error" and (recs[0]["width"], recs[0]["height"]) == (320, 320)
    check_working_size(320, 300, p.max_pixels)  # at the bound: fine


def test_decode_bound_refuses_huge_files_before_decoding(tmp_path: Path, monkeypatch) -> None:
    big = tmp_path / "big.png"
    cv2.imwrite(str(big), np.zeros((600, 500, 3), np.uint8))
    monkeypatch.setattr(torchrow.core.io, "MAX_DECODE_PIXELS", 500 * 599)
    with pytest.raises(ImageError, match="500x600"):
        load_image(big, 320)


def test_tracker_step_refuses_another_working_size() -> None:
    """Reproducer 8: `Tracker.step` reported `ok` with the old sky and rows."""
    a = render(FieldSpec(seed=1, width=320, height=180)).image
    b = render(FieldSpec(seed=1, width=320, height=240)).image
    p = Params(video_width=320)
    _, state = Tracker(p).step([a])
    with pytest.raises(ValueError) as e_ten:
        Tracker(p).step([b], state)
    _, rstate = ref.Tracker(p).step(a)
    with pytest.raises(ValueError) as e_ref:
        ref.Tracker(p).step(b, rstate)
    assert str(e_ten.value) == str(e_ref.value) == "frame of working size 320x240 in a sequence of 320x180"
    (res,), state = Tracker(p).step([a], state)  # the right size still goes on
    assert res.status != "error"


def test_veg_color_one_rule_in_both_paths() -> None:
    """Reproducer 10: a list was int64 for the tensor path but fine (floats truncated) for the reference."""
    img = render(FieldSpec(seed=1)).image
    x = torch.from_numpy(img).permute(2, 0, 1)[None].contiguous()
    det = CropRowDetector()
    want = ref.detect(img, veg_color=(112, 131, 73))
    for given in ([112, 131, 73], np.array([112, 131, 73]), torch.tensor([112, 131, 73]),
                  torch.tensor([[112, 131, 73]], dtype=torch.uint8)):
        got = det(x, veg_color=given).results()[0]
        assert got.veg_color == want.veg_color and got.status == want.status
        assert [h.to_list() for h in got.hough] == [h.to_list() for h in want.hough]
        assert ref.detect(img, veg_color=given[0] if getattr(given, "ndim", 1) == 2 else given).veg_color == (112, 131, 73)
    for bad, kind in (([112.7, 131, 73], TypeError), ([True, 1, 2], TypeError), ([112, 131, 256], ValueError),
                      ([112, 131], ValueError), ("abc", TypeError)):
        with pytest.raises(kind, match="veg_color"):
            det(x, veg_color=bad)
        with pytest.raises(kind, match="veg_color"):
            ref.detect(img, veg_color=bad)


@pytest.mark.skipif(torch.cuda.is_available(), reason="needs a machine without CUDA")
def test_missing_cuda_is_a_clear_error_at_construction() -> None:
    """Reproducer 10: `CropRowDetector(device="cuda")` failed later with an AssertionError."""
    for cls in (CropRowDetector, Tracker):
        with pytest.raises(ValueError, match=r"device: 'cuda'.*no CUDA"):
            cls(device="cuda")
    with pytest.raises(ValueError, match="device"):
        CropRowDetector(device="warp9")


def test_results_names_must_match_the_batch() -> None:
    """Reproducer 10: too few names raised IndexError."""
    img = render(FieldSpec(seed=1)).image
    x = torch.from_numpy(np.stack([img, img])).permute(0, 3, 1, 2).contiguous()
    batch = CropRowDetector()(x)
    with pytest.raises(ValueError, match="one name per image"):
        batch.results(["only one"])
    assert [r.name for r in batch.results(["a", "b"])] == ["a", "b"]


def test_detector_failure_record_carries_the_working_size(monkeypatch) -> None:
    """Reproducer 10: error records of detector failures had width and height 0."""
    img = render(FieldSpec(seed=1)).image

    def boom(self, *a, **k):
        raise RuntimeError("injected")

    monkeypatch.setattr(CropRowDetector, "forward", boom)
    (_, _, res, _), = run([("x", lambda: img)], "tensor", Params(), progress=False)
    assert res.status == "error" and "injected" in res.error and (res.width, res.height) == (320, 240)


def test_subsample_hash_cli_is_a_one_line_error(tmp_path: Path, capsys) -> None:
    """Reproducer 9: `--param subsample_hash=1.5` exited 0 with an error record per image."""
    from torchrow.apps.cli import main

    p = tmp_path / "a.png"
    cv2.imwrite(str(p), np.zeros((24, 32, 3), np.uint8))
    for value in ("1.5", "0", "x", str(2**70)):
        assert main(["detect", str(p), "--out", str(tmp_path / "r.jsonl"), "--param", f"subsample_hash={value}"]) == 2
        err = capsys.readouterr().err
        assert err.startswith("torchrow: error: Params.subsample_hash") and err.count("\n") == 1


def test_header_size_matches_the_decoded_image(tmp_path: Path) -> None:
    """The sequence size and the decode bound come from headers: EXIF rotation included."""
    from PIL import Image

    from torchrow.core.io import header_size

    im = Image.fromarray(np.zeros((30, 50, 3), np.uint8))
    exif = im.getexif()
    exif[0x0112] = 6  # rotate 90: decoded 30 wide, 50 high
    im.save(tmp_path / "rot.jpg", exif=exif)
    w, h = header_size(tmp_path / "rot.jpg")
    assert load_image(tmp_path / "rot.jpg").shape[:2] == (h, w) == (50, 30)
    cv2.imwrite(str(tmp_path / "p.png"), np.zeros((7, 9, 3), np.uint8))
    assert header_size(tmp_path / "p.png") == (9, 7)
    (tmp_path / "junk.png").write_bytes(b"not an image")
    assert header_size(tmp_path / "junk.png") is None


def test_file_size_bound_before_reading_the_bytes(tmp_path: Path) -> None:
    """Issue 26.11: a JPEG padded to 2 or 4 GB ended the run with MemoryError and the other
    image's record was lost. The padded files here are sparse: their size costs no disk, and
    the bound is checked on the size, before any byte is read."""
    from torchrow.apps.cli import main
    from torchrow.core.io import MAX_FILE_BYTES

    folder = tmp_path / "imgs"
    folder.mkdir()
    _ok, buf = cv2.imencode(".jpg", render(FieldSpec(seed=1, width=64, height=48)).image)
    for name, size in (("a_just_over.jpg", MAX_FILE_BYTES + 1), ("b_4gib.jpg", 4 * GIB)):
        (folder / name).write_bytes(buf.tobytes())
        os.truncate(folder / name, size)  # a valid JPEG, then zeros: it would decode
        with pytest.raises(ImageError, match=f"file of {size} bytes is larger than torchrow reads"):
            load_image(folder / name, 64)
    cv2.imwrite(str(folder / "c_field.png"), np.zeros((48, 64, 3), np.uint8))
    out = tmp_path / "r.jsonl"
    assert main(["detect", str(folder), "--out", str(out), "-q", "--param", "image_width=64"]) == 0
    recs = {r["name"]: r for r in map(json.loads, out.read_text().splitlines())}
    assert [recs[n]["status"] == "error" for n in sorted(recs)] == [True, True, False]
    assert "larger than torchrow reads" in recs["b_4gib.jpg"]["error"]


def test_read_binary_loaders_have_the_bounds_of_load_image(tmp_path: Path) -> None:
    """Issue 26: the object-storage reader (distributed.read_binary) had neither the working-size
    bound nor the file-size bound."""
    pytest.importorskip("pyarrow")
    from torchrow.engines.distributed import read_binary

    cv2.imwrite(str(tmp_path / "a_tall.png"), np.zeros((400, 4, 3), np.uint8))
    (tmp_path / "b_padded.jpg").write_bytes(b"\xff\xd8")
    os.truncate(tmp_path / "b_padded.jpg", 4 * GIB)
    for uri in (str(tmp_path), tmp_path.as_uri()):
        (_, tall), (_, padded) = read_binary(uri, width=64, max_pixels=100_000)
        with pytest.raises(ImageError, match="working size 64x6400"):
            tall()
        with pytest.raises(ImageError, match=f"file of {4 * GIB} bytes is larger than torchrow reads"):
            padded()
