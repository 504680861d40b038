"""Colour calibration by gradient descent (torchrow.nn.calibrate): targets, loss, fit, comparison."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torchrow import Params
from torchrow.apps.evaluate import compare_colors
from torchrow.evaluation.datasets import GroundTruth
from torchrow.evaluation.synthetic import FieldSpec, render
from torchrow.nn.calibrate import (
    band_loss,
    fit_vegetation_color,
    load_training_set,
    mask_precision,
    row_band_target,
)


def synthetic_set(seeds=(1, 2)):
    imgs, targets, regions = [], [], []
    for s in seeds:
        fld = render(FieldSpec(seed=s))
        gt = GroundTruth(c=fld.crp[:, 0], d=fld.crp[:, 1], v0=fld.sky, height=fld.image.shape[0])
        t, r = row_band_target(gt, fld.image.shape[1])
        imgs.append(fld.image)
        targets.append(t)
        regions.append(r)
    return (torch.from_numpy(np.stack(imgs)).permute(0, 3, 1, 2).contiguous(),
            torch.from_numpy(np.stack(targets)), torch.from_numpy(np.stack(regions)))


def test_row_band_target_geometry():
    h, w = 10, 40
    gt = GroundTruth(c=np.full(6, 2.0), d=np.full(6, 10.0), v0=4, height=h)
    t, r = row_band_target(gt, w, band=0.3)
    assert t.shape == r.shape == (h, w) and not t[:4].any() and r[4:].all() and not r[:4].any()
    # rows at x = 22 + 10 s, half-width 1.5 px: columns 21..23, 11..13, 31..33, 1..3
    expect = np.zeros(w, bool)
    for x0 in (2, 12, 22, 32):
        expect[x0 - 1:x0 + 2] = True
    assert np.array_equal(t[5], expect)
    with pytest.raises(ValueError, match="band"):
        row_band_target(gt, w, band=0)


def test_band_loss_values_and_gradient():
    targets = torch.zeros(1, 2, 4, dtype=torch.bool)
    targets[0, :, :2] = True
    regions = torch.ones(1, 2, 4, dtype=torch.bool)
    on = targets.double()
    loss, prec, frac = band_loss(on, targets, regions, min_fraction=0.1)
    assert float(prec[0]) == pytest.approx(1.0) and float(frac[0]) == 0.5 and float(loss) == pytest.approx(-1.0)
    uniform = torch.full((1, 2, 4), 0.5, dtype=torch.float64, requires_grad=True)
    loss, prec, _ = band_loss(uniform, targets, regions)
    assert float(prec[0]) == pytest.approx(0.5)
    loss.backward()
    # raising the mask on the rows lowers the loss, off the rows raises it
    assert (uniform.grad[targets] < 0).all() and (uniform.grad[~targets] > 0).all()
    small = torch.full((1, 2, 4), 1e-3, dtype=torch.float64)
    assert float(band_loss(small, targets, regions, min_fraction=0.02, penalty=1.0)[0]) > -0.5
    with pytest.raises(ValueError, match="equal shapes"):
        band_loss(uniform, targets[:, :1], regions)


def test_mask_precision():
    targets = torch.zeros(2, 2, 2, dtype=torch.bool)
    targets[:, 0] = True
    regions = torch.ones(2, 2, 2, dtype=torch.bool)
    masks = torch.tensor([[[True, False], [True, False]], [[False, False], [False, False]]])
    prec, frac = mask_precision(masks, targets, regions)
    assert prec.tolist() == [0.5, 0.0] and frac.tolist() == [0.5, 0.0]


def test_fit_lowers_the_loss_on_synthetic_fields():
    imgs, targets, regions = synthetic_set()
    fit = fit_vegetation_color(imgs, targets, regions, init_color=(90, 150, 60), steps=25, lr=0.05)
    h = fit.history
    assert len(h) == 26 and h[0]["step"] == 0 and fit.seconds > 0
    assert fit.color.dtype == np.uint8 and fit.color.shape == (3,)
    assert fit.init_color.tolist() == [90, 150, 60]
    assert min(x["loss"] for x in h[1:]) < h[0]["loss"]
    assert fit.temperature > 0 and fit.temperature == pytest.approx(h[-1]["temperature"])
    assert torch.equal(fit.module.color_uint8(), torch.from_numpy(fit.color))
    # zero steps: the colour is the initial one; default init = median of clustered colours
    fit0 = fit_vegetation_color(imgs[:1], targets[:1], regions[:1], steps=0)
    assert np.array_equal(fit0.color, fit0.init_color) and len(fit0.history) == 1


def test_fit_rejects_bad_input():
    imgs, targets, regions = synthetic_set(seeds=(1,))
    with pytest.raises(ValueError, match="images: expected uint8"):
        fit_vegetation_color(imgs.float(), targets, regions)
    with pytest.raises(ValueError, match="targets: expected bool"):
        fit_vegetation_color(imgs, targets[:, :5], regions)
    with pytest.raises(ValueError, match="stride"):
        fit_vegetation_color(imgs, targets, regions, stride=0)


@pytest.mark.data
def test_compare_colors_on_crbd(crbd_dir):
    from torchrow.evaluation.datasets import CRBD

    crbd = CRBD(crbd_dir)
    idx = crbd.indices("test")[:3]
    data = load_training_set(crbd, idx)
    assert data.images.shape == (3, 3, 240, 320) and data.targets.shape == (3, 240, 320)
    cmp = compare_colors(crbd, idx, {"default": None, "fixed": (100, 130, 70)}, Params(), batch_size=2)
    assert cmp.names == data.names
    assert (cmp.colors["fixed"] == np.array([100, 130, 70], np.uint8)).all()
    for arm in ("default", "fixed"):
        assert cmp.crda01[arm].shape == (3,) and ((cmp.crda01[arm] >= 0) & (cmp.crda01[arm] <= 1)).all()
        assert len(cmp.results[arm]) == 3
    # the default arm is the ordinary detector: same records as a plain run
    from torchrow import CropRowDetector

    plain = CropRowDetector(Params())(data.images).results(data.names)
    assert [r.to_record() for r in plain] == [r.to_record() for r in cmp.results["default"]]
    assert "default" in cmp.table() and "fixed" in cmp.table()
