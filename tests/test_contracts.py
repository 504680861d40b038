"""Every batched stage and the detector keep the same contract (tests/contracts.py):
batched equals unbatched, order, empty batch, inputs untouched, dtype and device kept,
CPU equals CUDA where a GPU is available. Stage-specific behaviour is tested beside each stage."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from contracts import check_batched_stage

import torchrow.functional as F
from torchrow import CropRowDetector, Params
from torchrow.evaluation.synthetic import FieldSpec, render

P = Params()


@pytest.fixture(scope="module")
def scene():
    """Four 96x128 fields (two with sky, one bare, one uniform green) and their stage inputs."""
    imgs = [render(FieldSpec(seed=1, width=128, height=96)).image,
            render(FieldSpec(seed=2, width=128, height=96, sky_rows=30)).image,
            np.full((96, 128, 3), (120, 96, 70), np.uint8),
            np.full((96, 128, 3), (40, 160, 40), np.uint8)]
    x = torch.from_numpy(np.stack(imgs)).permute(0, 3, 1, 2).contiguous()
    sky = F.sky.sky_row(x, P)
    color = F.color.vegetation_color(x, P)
    k = torch.tensor([4, 3, 9, 13])
    raw = F.vegetation.raw_mask(x, color, k, sky)
    veg = F.vegetation.remove_bushy(raw, sky, P)
    hin, _ = F.vegetation.hough_input(veg, sky, P)
    return dict(x=x, sky=sky, color=color, k=k, raw=raw, veg=veg, hin=hin,
                info0=torch.tensor([0.01, 0.3, 0.0, 0.2], dtype=torch.float64),
                gray=F.kernels.gray(x))


B = True  # batched input


def test_sky_stages(scene):
    x = scene["x"]
    check_batched_stage(F.kernels.gray, (x, B), name="gray")
    check_batched_stage(F.sky.sky_row, (x, B), P, name="sky_row")
    check_batched_stage(F.sky.sky_mask, (x, B), P, name="sky_mask")
    check_batched_stage(F.sky.horizon_mask, (x, B), P, name="horizon_mask")
    check_batched_stage(F.sky.SkyRow(P), (x, B), name="SkyRow")


def test_opencv_kernels(scene):
    g = scene["gray"]
    check_batched_stage(F.sky.box_blur, (g, B), (9, 3), name="box_blur")
    check_batched_stage(F.sky.median_blur, (g, B), 5, name="median_blur")
    check_batched_stage(F.sky.laplacian, (g, B), name="laplacian")
    check_batched_stage(F.sky.erode_rect, (g, B), (9, 3), name="erode_rect")
    check_batched_stage(F.sky.column_median, (scene["veg"], B), 19, name="column_median")


def test_color_stages(scene):
    x = scene["x"]
    check_batched_stage(F.color.vegetation_color, (x, B), P, name="vegetation_color")
    check_batched_stage(F.color.vegetation_clusters, (x, B), P, name="vegetation_clusters")
    check_batched_stage(F.color.VegetationColor(P), (x, B), name="VegetationColor")


def test_vegetation_stages(scene):
    s = scene
    check_batched_stage(F.vegetation.lab, (s["x"], B), name="lab")
    check_batched_stage(F.vegetation.raw_mask, (s["x"], B), (s["color"], B), (s["k"], B), (s["sky"], B),
                        name="raw_mask")
    check_batched_stage(F.vegetation.raw_fraction, (s["raw"], B), (s["sky"], B), name="raw_fraction")
    check_batched_stage(F.vegetation.adapt_k, (s["x"], B), (s["color"], B), (s["sky"], B), (s["info0"], B), P,
                        name="adapt_k")
    check_batched_stage(F.vegetation.remove_bushy, (s["raw"], B), (s["sky"], B), P, name="remove_bushy")
    check_batched_stage(F.vegetation.canny_binary, (s["veg"], B), (s["sky"], B), P, name="canny_binary")
    check_batched_stage(F.vegetation.density, (s["veg"], B), (s["sky"], B), name="density")
    check_batched_stage(F.vegetation.hough_input, (s["veg"], B), (s["sky"], B), P, name="hough_input")
    check_batched_stage(F.vegetation.VegetationMask(P), (s["x"], B), (s["color"], B), (s["sky"], B),
                        name="VegetationMask")


def test_line_search(scene):
    check_batched_stage(F.hough.votes, (scene["hin"], B), P, name="hough.votes")
    check_batched_stage(F.vanishing.find_lines, (scene["hin"], B), P, name="find_lines")


def test_detector(scene):
    # an engine computes on its own device (a constructor argument): one detector per device
    dets: dict[str, CropRowDetector] = {}

    def det(x, c=None):
        d = dets.setdefault(x.device.type, CropRowDetector(P, device=x.device.type))
        return d(x) if c is None else d(x, veg_color=c)

    # continuous outputs (VP, rows) agree within 1e-6 px on a GPU ("Identical results")
    check_batched_stage(det, (scene["x"], B), name="CropRowDetector", device_tol=1e-6)
    check_batched_stage(det, (scene["x"], B), (scene["color"], B), name="CropRowDetector(veg_color)", device_tol=1e-6)
