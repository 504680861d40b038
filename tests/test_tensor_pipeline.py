"""End-to-end parity: the batched tensor detector equals the per-image reference.

"Equal" is ALGORITHM.md's definition: every discrete output identical, vanishing point and
row parameters within 1e-6 px.
"""

from __future__ import annotations

import math
import random

import numpy as np
import pytest
import torch

from torchrow import Params
from torchrow.core.results import ImageResult
from torchrow.engines.detector import CropRowDetector
from torchrow.evaluation.synthetic import FieldSpec, render
from torchrow.reference import detect

TOL = 1e-6


def assert_same(ref: ImageResult, got: ImageResult, label: str = "") -> None:
    """ALGORITHM.md "Identical results" between two per-image results."""
    a, b = ref.to_record(), got.to_record()
    rows_a, rows_b = a.pop("rows"), b.pop("rows")
    vp_a, vp_b = a.pop("vp"), b.pop("vp")
    a.pop("name"), b.pop("name")
    assert a == b, f"{label}: discrete fields differ"
    assert (vp_a is None) == (vp_b is None), f"{label}: vp presence"
    if vp_a is not None:
        assert max(abs(x - y) for x, y in zip(vp_a, vp_b)) <= TOL, f"{label}: vp {vp_a} vs {vp_b}"
    assert [(r["valid"], r["reason"]) for r in rows_a] == [(r["valid"], r["reason"]) for r in rows_b], label
    assert [r.hypothesis for r in ref.rows] == [r.hypothesis for r in got.rows], f"{label}: RANSAC winners"
    for ra, rb in zip(rows_a, rows_b):
        for key in ("a", "b"):
            if ra[key] is None or rb[key] is None:
                assert ra[key] is None and rb[key] is None, f"{label}: row {key} NaN mismatch"
            else:
                assert math.isclose(ra[key], rb[key], abs_tol=TOL if key == "b" else TOL / 1000), \
                    f"{label}: row {key} {ra[key]} vs {rb[key]}"


def to_batch(images: list[np.ndarray]) -> torch.Tensor:
    return torch.from_numpy(np.stack(images)).permute(0, 3, 1, 2).contiguous()


@pytest.fixture(scope="module")
def detector() -> CropRowDetector:
    return CropRowDetector(Params())


def _adversarial(h: int = 240, w: int = 320) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(7)
    soil = np.empty((h, w, 3), np.uint8)
    soil[:] = (120, 95, 70)
    green = np.zeros((h, w, 3), np.uint8)
    green[:] = (0, 200, 0)
    noise = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
    bushy = render(FieldSpec(seed=11, width=w, height=h)).image.copy()
    bushy[h // 3:, :, :] = np.where(rng.random((h - h // 3, w, 1)) < 0.5, (40, 160, 40), bushy[h // 3:]).astype(np.uint8)
    return {"soil": soil, "green": green, "noise": noise, "bushy": bushy,
            "field": render(FieldSpec(seed=5, width=w, height=h)).image,
            "sky_field": render(FieldSpec(seed=6, width=w, height=h, sky_rows=60)).image}


def test_synthetic_and_adversarial_batch_equals_reference(detector: CropRowDetector) -> None:
    cases = _adversarial()
    names = list(cases)
    got = detector(to_batch([cases[n] for n in names])).results(names)
    for name, res in zip(names, got):
        assert_same(detect(cases[name]), res, name)
    by = dict(zip(names, got))
    assert by["soil"].status == "no_vegetation" and by["green"].status == "no_vegetation"
    assert by["field"].status in ("ok", "invalid") and any(r.valid for r in by["field"].rows)


@pytest.mark.parametrize("size", [(203, 320), (1, 320), (7, 320), (240, 320)])
def test_odd_sizes_equal_reference(detector: CropRowDetector, size: tuple[int, int]) -> None:
    h, w = size
    imgs = [np.ascontiguousarray(render(FieldSpec(seed=s, width=w)).image[:h]) for s in (1, 2)]
    for name, im, res in zip(("a", "b"), imgs, detector(to_batch(imgs)).results()):
        assert_same(detect(im), res, f"{size} {name}")


def test_empty_batch(detector: CropRowDetector) -> None:
    out = detector(torch.zeros((0, 3, 240, 320), dtype=torch.uint8))
    assert len(out) == 0 and out.results() == []


def test_bad_input_errors(detector: CropRowDetector) -> None:
    with pytest.raises(ValueError, match=r"\(B, 3, H, W\)"):
        detector(torch.zeros((3, 240, 320), dtype=torch.uint8))
    with pytest.raises(ValueError, match="uint8"):
        detector(torch.zeros((1, 3, 240, 320), dtype=torch.float32))
    with pytest.raises(TypeError):
        detector(np.zeros((1, 3, 240, 320), np.uint8))  # type: ignore[arg-type]


def test_detect_accepts_lists_of_arrays_and_paths(detector: CropRowDetector, tmp_path) -> None:
    import cv2

    f = render(FieldSpec(seed=4, width=640, height=480)).image  # resized to 320 wide, as the reference
    p = tmp_path / "f.png"
    cv2.imwrite(str(p), cv2.cvtColor(f, cv2.COLOR_RGB2BGR))
    ref = detect(f)
    for inp in ([f], [p]):
        assert_same(ref, detector.detect(inp).results()[0], str(type(inp[0])))


@pytest.mark.data
def test_crbd_batch_composition_does_not_matter(detector: CropRowDetector, crbd_dir) -> None:
    """Shuffled batches of 1, 7 and 64 give the same records (and equal the reference)."""
    from torchrow.evaluation.datasets import CRBD

    ds = CRBD(crbd_dir)
    idx = list(range(0, len(ds), 4))[:40]
    imgs = [ds.image(i) for i in idx]
    refs = [detect(im) for im in imgs]
    for bs in (64, 7, 1):
        order = list(range(len(idx)))
        random.Random(bs).shuffle(order)
        if bs == 1:
            order = order[:10]
        got: dict[int, ImageResult] = {}
        for s in range(0, len(order), bs):
            chunk = order[s:s + bs]
            for j, res in zip(chunk, detector(to_batch([imgs[j] for j in chunk])).results()):
                got[j] = res
        for j, res in got.items():
            assert_same(refs[j], res, f"{ds.names[idx[j]]} (batch {bs})")


def _crbd_equal_reference(detector: CropRowDetector, crbd_dir, every: int, first: int = 0) -> None:
    from torchrow.evaluation.datasets import CRBD

    ds = CRBD(crbd_dir)
    idx = list(range(first, len(ds), every))
    imgs = [ds.image(i) for i in idx]
    for s in range(0, len(imgs), 64):
        for j, res in enumerate(detector(to_batch(imgs[s:s + 64])).results()):
            assert_same(detect(imgs[s + j]), res, ds.names[idx[s + j]])


@pytest.mark.data
@pytest.mark.slow
def test_every_eighth_crbd_image_equals_reference(detector: CropRowDetector, crbd_dir) -> None:
    # images 2, 10, 18, ... (35; the batch-composition test above takes 0, 4, 8, ...); all 281:
    # the heavy test below
    _crbd_equal_reference(detector, crbd_dir, 8, 2)


@pytest.mark.heavy
@pytest.mark.data
def test_all_crbd_images_equal_reference(detector: CropRowDetector, crbd_dir) -> None:
    _crbd_equal_reference(detector, crbd_dir, 1)


def test_batch_without_any_vegetation(detector: CropRowDetector) -> None:
    """A batch where no image has a single band pixel (every stage sees empty lists)."""
    soil = _adversarial()["soil"]
    got = detector(to_batch([soil, soil[:, ::-1].copy()])).results()
    assert [r.status for r in got] == ["no_vegetation", "no_vegetation"]
    for im, res in zip([soil, soil[:, ::-1].copy()], got):
        assert_same(detect(im), res, "soil")


@pytest.mark.data
def test_rover_frames_equal_reference(detector: CropRowDetector, data_dir) -> None:
    """Real 1280x720 rover frames (another working size: 320x180) through both paths."""
    from torchrow.core.io import load_image

    frames = sorted((data_dir / "caterra_video").glob("rgb*.jpg"))[::20]
    if not frames:
        pytest.skip("caterra_video frames not found")
    imgs = [load_image(f, 320) for f in frames]
    assert imgs[0].shape == (180, 320, 3)
    for f, im, res in zip(frames, imgs, detector(to_batch(imgs)).results()):
        assert_same(detect(im), res, f.name)


def test_given_vegetation_color_equals_reference(detector: CropRowDetector) -> None:
    """A fixed colour (calibrated once, or a video's frame 0) replaces clustering in both paths."""
    images = [render(FieldSpec(seed=s)).image for s in (3, 4)]
    color = (40, 120, 30)
    got = detector(to_batch(images), veg_color=torch.tensor(color, dtype=torch.uint8)).results()
    for i, (im, g) in enumerate(zip(images, got)):
        ref = detect(im, veg_color=color)
        assert ref.veg_color == color
        assert_same(ref, g, f"image {i}")
    per_image = torch.tensor([color, (0, 255, 0)], dtype=torch.uint8)
    got = detector(to_batch(images), veg_color=per_image).results()
    assert_same(detect(images[1], veg_color=(0, 255, 0)), got[1], "per-image colour")
    # one rule in both paths (issue 11): integers of any dtype, never floats, in [0, 255]
    assert_same(detect(images[0], veg_color=color),
                detector(to_batch(images), veg_color=torch.tensor(color)).results()[0], "int64 colour")
    with pytest.raises(TypeError, match="veg_color"):
        detector(to_batch(images), veg_color=torch.tensor(color, dtype=torch.float32))
    with pytest.raises(ValueError, match=r"\(3,\) or \(B, 3\)"):
        detector(to_batch(images), veg_color=torch.zeros(3, 3, dtype=torch.uint8))
    with pytest.raises(ValueError, match=r"\[0, 255\]"):
        detect(images[0], veg_color=(0, 300, 0))


def test_worker_threads_do_not_change_results() -> None:
    """Chunks run concurrently on single-threaded workers; the records and the caller's
    thread count are unchanged."""
    cases = _adversarial()
    batch = to_batch(list(cases.values()))
    serial = CropRowDetector(chunk=2, workers=1)(batch).results()
    threads = torch.get_num_threads()
    parallel = CropRowDetector(chunk=2, workers=3)(batch).results()
    assert torch.get_num_threads() == threads
    for a, b in zip(serial, parallel):
        assert a.to_record() == b.to_record()
    with pytest.raises(ValueError, match="workers"):
        CropRowDetector(workers=0)
