"""Differentiable blocks (torchrow.nn): gradcheck, soft -> hard convergence, equality with the
hard stages, guards, and no effect on the hard pipeline."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from torch.autograd import gradcheck
from torch.func import functional_call

from torchrow import Params
from torchrow.core.tables import hough_theta, rgb_to_lab
from torchrow.functional import hough as fhough
from torchrow.functional import vanishing as fvan
from torchrow.nn import (
    HoughVoting,
    SoftVegetationMask,
    WeightedVanishingPoint,
    hough_voting,
    soft_lab_box,
    soft_vegetation_mask,
    weighted_vanishing_point,
)
from torchrow.reference.vegetation import raw_mask as ref_raw_mask

F64 = torch.float64
COLOR = (60, 120, 40)


def near_color_images(seed: int, b: int = 2, h: int = 12, w: int = 14, spread: int = 6) -> torch.Tensor:
    """uint8 (B, 3, H, W) colours scattered around COLOR: a mix of pixels in and out of the box."""
    g = torch.Generator().manual_seed(seed)
    base = torch.tensor(COLOR, dtype=torch.int64).view(1, 3, 1, 1)
    noise = torch.randint(-spread, spread + 1, (b, 3, h, w), generator=g)
    return (base + noise).clamp(0, 255).to(torch.uint8)


# --- soft vegetation mask --------------------------------------------------------------------
def test_soft_mask_shapes_dtype_and_range():
    img = near_color_images(0)
    m = SoftVegetationMask(COLOR, temperature=0.5)
    for dtype in (torch.float32, F64):
        x = img.to(dtype) / 255
        before = x.clone()
        with torch.no_grad():
            out = m(x)
        assert out.shape == (2, 12, 14) and out.dtype == dtype and out.device == x.device
        assert float(out.min()) >= 0 and float(out.max()) <= 1
        assert torch.equal(x, before)  # input not modified
    assert m(torch.zeros((0, 3, 5, 6))).shape == (0, 5, 6)
    assert torch.equal(m.color_uint8(), torch.tensor(COLOR, dtype=torch.uint8))
    assert math.isclose(float(m.temperature.detach()), 0.5, rel_tol=1e-12)


def test_soft_mask_sky_rows_are_zero_and_from_lab_agrees():
    img = near_color_images(1)
    m = SoftVegetationMask(COLOR, temperature=1.0).requires_grad_(False)
    x = img.to(F64) / 255
    sky = torch.tensor([0, 5])
    out = m(x, sky=sky)
    assert float(out[1, :5].abs().max()) == 0.0
    assert torch.equal(out[0], m(x)[0])
    import kornia

    torch.testing.assert_close(m.from_lab(kornia.color.rgb_to_lab(x), sky=sky), out, rtol=0, atol=1e-12)


def test_hard_is_the_pipeline_mask():
    img = near_color_images(2)
    m = SoftVegetationMask(COLOR)
    hard = m.hard(img, sky=torch.tensor([0, 3]))
    for b, s in enumerate((0, 3)):
        ref = ref_raw_mask(img[b].permute(1, 2, 0).numpy(), COLOR, 4, s)
        assert np.array_equal(hard[b].numpy(), ref)
    assert 0 < int(hard.sum()) < hard.numel()  # the fixture mixes inside and outside pixels


def box_margin(img: torch.Tensor, color: tuple[int, int, int], k: float) -> np.ndarray:
    """Signed distance (LAB units) of every pixel to the hard box boundary, > 0 inside."""
    lab = rgb_to_lab(img.permute(0, 2, 3, 1).numpy())  # (B, H, W, 3), the pipeline's LAB bits
    c = rgb_to_lab(np.array(color, dtype=np.uint8))
    return np.minimum(lab - (c - k), (c + k) - lab).min(axis=-1)


def test_soft_mask_tends_to_hard_mask():
    """Bound of soft_lab_box: |soft - hard| <= 6 exp(-m/T) at margin >= m from the box boundary."""
    img = near_color_images(3, b=4, h=24, w=24, spread=8)
    x = img.to(F64) / 255
    margin = box_margin(img, COLOR, 4.0)
    hard = SoftVegetationMask(COLOR).hard(img).numpy()
    assert np.array_equal(hard, margin >= 0)  # margin sign agrees with the pipeline's mask
    prev = None
    for t in (1.0, 0.3, 0.1, 0.03, 0.01, 1e-3, 1e-4):
        soft = SoftVegetationMask(COLOR, temperature=t)(x).detach().numpy()
        err = np.abs(soft - hard)
        for m in (0.01, 0.05, 0.2, 1.0):
            far = np.abs(margin) >= m
            if far.any():
                # 1e-9: the soft path's LAB (kornia on this layout) may differ from the table's by ulps
                assert err[far].max() <= 6 * math.exp(-m / t) + 1e-9, (t, m)
        mean = float(err.mean())
        assert prev is None or mean < prev
        prev = mean
    # at T = 1e-4 every pixel farther than 2e-3 LAB units from the boundary agrees after rounding
    far = np.abs(margin) > 2e-3
    assert np.array_equal(soft[far] > 0.5, hard[far])
    assert far.mean() > 0.99


def test_soft_mask_gradcheck_images_color_temperature():
    g = torch.Generator().manual_seed(4)
    color = (0.25 + 0.5 * torch.rand(3, generator=g, dtype=F64)).requires_grad_()
    x = (color.detach().view(1, 3, 1, 1) + 0.03 * torch.randn(2, 3, 3, 4, generator=g, dtype=F64))
    x = x.clamp(0.1, 0.9).requires_grad_()
    temp = torch.tensor(2.0, dtype=F64, requires_grad=True)
    assert gradcheck(lambda a, c, t: soft_vegetation_mask(a, c, 4.0, t), (x, color, temp))
    # per-image k and temperature, and the LAB box alone
    lab = (torch.tensor([50.0, -20.0, 30.0], dtype=F64).view(1, 3, 1, 1)
           + 3 * torch.randn(2, 3, 3, 4, generator=g, dtype=F64)).requires_grad_()
    center = torch.tensor([[50.0, -20.0, 30.0], [51.0, -19.0, 29.0]], dtype=F64, requires_grad=True)
    k = torch.tensor([4.0, 3.0], dtype=F64, requires_grad=True)
    tt = torch.tensor([1.0, 0.7], dtype=F64, requires_grad=True)
    assert gradcheck(soft_lab_box, (lab, center, k, tt))


def test_soft_mask_module_gradcheck_parameters():
    m = SoftVegetationMask(COLOR, temperature=1.5)
    x = near_color_images(5, b=1, h=3, w=4).to(F64) / 255
    names = ("color_logit", "log_temperature")
    params = tuple(getattr(m, n).detach().clone().requires_grad_() for n in names)

    def f(*p):
        return functional_call(m, dict(zip(names, p)), (x,))

    assert gradcheck(f, params)
    out = m(x).sum()
    out.backward()
    assert m.color_logit.grad is not None and m.log_temperature.grad is not None


def test_soft_mask_frozen_parameters_are_buffers():
    m = SoftVegetationMask(COLOR, learn_color=False, learn_temperature=False)
    assert list(m.parameters()) == []
    assert {"color_logit", "log_temperature", "k"} <= set(dict(m.named_buffers()))
    m2 = SoftVegetationMask(COLOR, learn_temperature=False)
    assert [n for n, _ in m2.named_parameters()] == ["color_logit"]


def test_soft_mask_extreme_colors_round_back():
    for c in ((0, 0, 0), (255, 255, 255), (0, 255, 0)):
        assert tuple(SoftVegetationMask(c).color_uint8().tolist()) == c


@pytest.mark.parametrize(("bad", "match"), [
    (torch.zeros(2, 3, 4, 4, dtype=torch.uint8), "floating-point tensor \\(B, 3, H, W\\).*uint8"),
    (torch.zeros(3, 4, 4), "\\(B, 3, H, W\\).*\\(3, 4, 4\\)"),
    (torch.zeros(1, 4, 4, 4), "\\(B, 3, H, W\\).*\\(1, 4, 4, 4\\)"),
    (np.zeros((1, 3, 4, 4)), "got ndarray"),
])
def test_soft_mask_bad_input(bad, match):
    with pytest.raises(ValueError, match=match):
        SoftVegetationMask(COLOR)(bad)


def test_soft_mask_bad_arguments():
    x = torch.rand(2, 3, 4, 4)
    with pytest.raises(ValueError, match="sky: expected an integer tensor of shape \\(2,\\)"):
        SoftVegetationMask()(x, sky=torch.zeros(2))
    with pytest.raises(ValueError, match="color: expected"):
        soft_vegetation_mask(x, torch.rand(4))
    with pytest.raises(ValueError, match="temperature: expected a finite number > 0"):
        SoftVegetationMask(temperature=0.0)
    with pytest.raises(ValueError, match="color_rgb"):
        SoftVegetationMask(color_rgb=(1, 2))
    with pytest.raises(ValueError, match="uint8"):
        SoftVegetationMask().hard(x)


# --- Hough voting ----------------------------------------------------------------------------
@pytest.mark.parametrize(("h", "w", "step"), [(9, 13, 1), (20, 16, 5), (1, 1, 1)])
def test_hough_voting_equals_hard_votes(h, w, step):
    params = Params(theta_step=step)
    g = torch.Generator().manual_seed(h * w)
    mask = torch.rand(3, h, w, generator=g) < 0.3
    mask[1] = False
    hv = HoughVoting(h, w, params)
    for dtype in (F64, torch.float32):
        weights = mask.to(dtype)
        acc = hv(weights)
        ref = fhough.votes(mask, params)
        assert acc.shape == ref.shape == (3, params.n_theta, 2 * hv.d + 1) and acc.dtype == dtype
        assert torch.equal(acc, ref.to(dtype))
        assert torch.equal(weights, mask.to(dtype))  # input not modified
    assert hv(torch.zeros(0, h, w)).shape == (0, params.n_theta, hv.n_rho)


def test_hough_voting_is_linear_and_small_chunks_agree(monkeypatch):
    import torchrow.nn.blocks as tnn

    hv = HoughVoting(7, 9, Params(theta_step=3))
    g = torch.Generator().manual_seed(7)
    a, b = torch.rand(2, 7, 9, generator=g, dtype=F64), torch.rand(2, 7, 9, generator=g, dtype=F64)
    full = hv(2 * a + b)
    torch.testing.assert_close(full, 2 * hv(a) + hv(b), rtol=1e-12, atol=1e-12)
    monkeypatch.setattr(tnn, "_VOTE_CHUNK", 60 * 2)  # forces one pixel per chunk
    torch.testing.assert_close(hv(2 * a + b), full, rtol=1e-12, atol=1e-12)
    # every weight lands once per angle: total mass per angle = sum of weights
    torch.testing.assert_close(full.sum(dim=2), (2 * a + b).sum(dim=(1, 2)).unsqueeze(1).expand(2, 60))


def test_hough_voting_gradcheck():
    hv = HoughVoting(5, 6, Params(theta_step=15))
    w = torch.rand(2, 5, 6, dtype=F64, requires_grad=True)
    assert gradcheck(hv, (w,))
    assert gradcheck(lambda x: hough_voting(x, hv.cells.long(), hv.n_rho), (w,))


def test_hough_voting_axes():
    hv = HoughVoting(10, 12, Params(theta_step=30))
    np.testing.assert_array_equal(hv.theta().numpy(), hough_theta(Params(theta_step=30)))
    assert hv.rho().shape == (hv.n_rho,) and float(hv.rho()[hv.d]) == 0.0


def test_hough_voting_bad_input():
    hv = HoughVoting(5, 6)
    with pytest.raises(ValueError, match=r"expected a floating-point tensor \(B, 5, 6\), got torch\.float32 \(1, 6, 5\)"):
        hv(torch.zeros(1, 6, 5))
    with pytest.raises(ValueError, match=r"got torch\.bool"):
        hv(torch.zeros(1, 5, 6, dtype=torch.bool))
    with pytest.raises(ValueError, match="height, width"):
        HoughVoting(0, 5)


# --- weighted vanishing point -------------------------------------------------------------------
def hard_lines(seed: int, b: int = 16, s: int = 5):
    """Random hard Hough lines as the detector holds them: compact at the front."""
    g = torch.Generator().manual_seed(seed)
    allowed = torch.tensor([j for j in range(180) if abs(j - 90) >= 25])
    theta = allowed[torch.randint(0, len(allowed), (b, s), generator=g)]
    rho = torch.randint(-300, 300, (b, s), generator=g)
    weight = torch.randint(1, 200, (b, s), generator=g)
    held = torch.randint(0, s + 1, (b,), generator=g)
    valid = torch.arange(s).unsqueeze(0) < held.unsqueeze(1)
    return theta, rho, weight, valid


def test_weighted_vp_equals_hard_vanishing_point():
    params = Params()
    theta, rho, weight, valid = hard_lines(8)
    ref = fvan.vanishing_point(theta, rho, weight, valid, params)
    rad = torch.from_numpy(hough_theta(params))[theta]
    args = (rad, rho.to(F64), weight.to(F64), valid)
    before = [a.clone() for a in args]
    vp, ok = WeightedVanishingPoint()(*args)
    assert vp.shape == (16, 2) and vp.dtype == F64 and ok.dtype == torch.bool
    assert torch.equal(ok, ref.ok)
    assert ok.any() and (~ok).any()
    torch.testing.assert_close(vp[:, 0], ref.x, rtol=0, atol=1e-7)
    torch.testing.assert_close(vp[:, 1], ref.y, rtol=0, atol=1e-7)
    assert float(vp[~ok].abs().max()) == 0.0
    assert all(torch.equal(a, b) for a, b in zip(args, before))
    # float32 in, float32 out
    vp32, _ = weighted_vanishing_point(rad.float(), rho.float(), weight.float(), valid)
    assert vp32.dtype == torch.float32


def test_weighted_vp_gradcheck():
    g = torch.Generator().manual_seed(9)
    theta = torch.cat([0.3 + 0.8 * torch.rand(3, 2, generator=g, dtype=F64),
                       2.0 + 0.8 * torch.rand(3, 2, generator=g, dtype=F64)], 1).requires_grad_()
    rho = (100 * torch.randn(3, 4, generator=g, dtype=F64)).requires_grad_()
    weight = (1 + torch.rand(3, 4, generator=g, dtype=F64)).requires_grad_()
    valid = torch.tensor([[True, True, True, True], [True, True, False, True], [True, False, False, False]])
    assert gradcheck(lambda t, r, w: weighted_vanishing_point(t, r, w, valid)[0], (theta, rho, weight))
    vp, ok = weighted_vanishing_point(theta, rho, weight, valid)
    assert ok.tolist() == [True, True, False]
    vp.sum().backward()
    assert torch.isfinite(theta.grad).all() and float(theta.grad[2].abs().max()) == 0.0


def test_weighted_vp_recovers_exact_intersection():
    x0, y0 = 150.0, -40.0
    theta = torch.tensor([[0.3, 0.9, 2.2, 2.7]], dtype=F64)
    rho = x0 * torch.cos(theta) + y0 * torch.sin(theta)
    vp, ok = weighted_vanishing_point(theta, rho, torch.rand(1, 4, dtype=F64) + 0.1)
    assert bool(ok[0])
    torch.testing.assert_close(vp[0], torch.tensor([x0, y0], dtype=F64), rtol=0, atol=1e-9)


def test_weighted_vp_bad_input():
    t = torch.zeros(2, 3)
    with pytest.raises(ValueError, match="equal shapes"):
        weighted_vanishing_point(t, torch.zeros(2, 4), t)
    with pytest.raises(ValueError, match="valid: expected a bool tensor \\(2, 3\\)"):
        weighted_vanishing_point(t, t, t, torch.ones(2, 3))
    with pytest.raises(ValueError, match="theta: expected a floating-point tensor"):
        weighted_vanishing_point(torch.zeros(2, 3, dtype=torch.int64), t, t)


# --- the hard pipeline is unaffected --------------------------------------------------------------
def test_hard_pipeline_unchanged_by_nn_blocks():
    from torchrow import CropRowDetector
    from torchrow.evaluation.synthetic import FieldSpec, render

    fld = render(FieldSpec(seed=11))
    img = torch.from_numpy(fld.image).permute(2, 0, 1).unsqueeze(0).contiguous()
    det = CropRowDetector(Params())
    before = [r.to_record() for r in det(img).results()]
    grad_mode, default_dtype = torch.is_grad_enabled(), torch.get_default_dtype()
    # use every block, with gradients, on the same image
    m = SoftVegetationMask(before[0]["veg_color"], temperature=0.5)
    soft = m(img.to(F64) / 255)
    acc = HoughVoting(img.shape[2], img.shape[3])(soft)
    vp, _ = WeightedVanishingPoint()(torch.tensor([[0.5, 2.6]], dtype=F64), acc.amax(dim=2)[:, :2],
                                     torch.ones(1, 2, dtype=F64))
    (acc.sum() + vp.sum()).backward()
    assert torch.is_grad_enabled() == grad_mode and torch.get_default_dtype() == default_dtype
    assert [r.to_record() for r in det(img).results()] == before
    # the learned-colour entry point of the pipeline takes the block's colour unchanged
    fixed = det(img, veg_color=m.color_uint8()).results()[0]
    assert tuple(fixed.veg_color) == tuple(before[0]["veg_color"])
    assert fixed.to_record() == before[0]
