"""The exportable formulations (torchrow.onnx.graphs) run eagerly in torch, against
the eager stages: no onnx needed, no export, seconds per test.

The ONNX tests (test_export*.py) check that onnxruntime runs these graphs to the same
results; these check the formulations themselves on the inputs that stress them: the
scatter-free vote, the static adaptive k and the trig-free row finish.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from test_tensor_lines import _adversarial_masks

import torchrow
from torchrow import Params
from torchrow.core.tables import lab_table_torch, pack_rgb
from torchrow.evaluation.synthetic import FieldSpec, sequence
from torchrow.functional import hough as fhough
from torchrow.functional import ransac as fransac
from torchrow.functional import sky as fsky
from torchrow.functional import vanishing as fvan
from torchrow.functional import vegetation as fveg
from torchrow.functional.tracking import TrackerState
from torchrow.onnx import graphs as static
from torchrow.onnx.checks import step_differences

P = Params()


def test_scatter_free_votes_equal_scatter_votes() -> None:
    """Prefix sums gathered at constant run ends == scatter-add votes, on the pickable angles."""
    for h, w in ((240, 320), (37, 53)):
        masks = torch.from_numpy(np.stack([m[:h, :w] for m in _adversarial_masks()]))
        tables = fhough.vote_tables(h, w, P)
        got = fhough.prefix_votes(masks.reshape(len(masks), -1), tables)  # (B, A, 2D+1)
        ref = fhough.votes(masks, P)  # (B, n_theta, 2D+1)
        assert torch.equal(got.to(torch.int64), ref.index_select(1, tables.angles).to(torch.int64))


@settings(deadline=None, max_examples=40, suppress_health_check=[HealthCheck.too_slow])
@given(sxx=st.floats(0, 1e6), syy=st.floats(0, 1e6), r=st.floats(-1, 1))
def test_trig_free_direction_matches_atan2(sxx: float, syy: float, r: float) -> None:
    """The closed-form eigenvector equals (cos, sin) of the spec's atan2 half-angle to 1e-12."""
    sxy = r * math.sqrt(sxx * syy)  # a valid (positive semi-definite) scatter
    t = [torch.tensor([v], dtype=torch.float64) for v in (sxx, syy, sxy)]
    dx0, dy0 = fransac.principal_direction(*t)
    dx1, dy1 = fransac.principal_direction(*t, trig_free=True)
    if abs(float(dy0)) < 1e-9:  # a horizontal direction: the sign convention may differ by rounding
        assert abs(abs(float(dx0)) - abs(float(dx1))) < 1e-12 and abs(float(dy1)) < 1e-9
    else:
        assert abs(float(dx0 - dx1)) < 1e-12 and abs(float(dy0 - dy1)) < 1e-12
    assert float(dy1) >= 0


def test_trig_free_validity_equals_atan2_rules() -> None:
    """Rows built to sit on each side of the horizon and parallel thresholds get the same
    reasons with and without atan2."""
    ang = torch.tensor([[1.2, 1.2 + P.min_angle_diff * 0.9, 1.9, P.horizon_angle * 0.8, 2.5],
                        [0.5, 0.5 + P.min_angle_diff * 1.1, 2.0, P.horizon_angle * 1.2, 1.4]], dtype=torch.float64)
    dx, dy = torch.cos(ang), torch.sin(ang)
    cx = torch.tensor([[20.0, 120.0, 220.0, 160.0, 300.0]] * 2, dtype=torch.float64)
    cy = torch.full_like(cx, 150.0)
    hyp = torch.zeros((2, 5), dtype=torch.int64)
    ok = torch.ones((2, 5), dtype=torch.bool)
    band = torch.full((2,), P.hough_band_px(320), dtype=torch.int64)
    fit = fransac.RowFit(cx, cy, dx, dy, hyp, ok)
    a = fransac.validate_rows(fit, ok, 240, band, P)
    b = fransac.validate_rows(fit, ok, 240, band, P, trig_free=True)
    assert torch.equal(a.reason, b.reason) and torch.equal(a.valid, b.valid)
    assert set(a.reason.flatten().tolist()) >= {0, 2, 3}  # valid, horizon and parallel all occur


@pytest.mark.parametrize("band_tier", ["default", "short", "whole"])
def test_static_detector_equals_crop_row_detector(band_tier: str) -> None:
    """StaticDetector + host finish == CropRowDetector on synthetic fields (reduced steps),
    with the band points on the short list, on the whole list, and on the default choice."""
    small = Params(n_rows=3, max_outliers=2)
    fields = [FieldSpec.at_size(320, 240, n_rows=5, seed=s) for s in (1, 4)]
    x = torch.from_numpy(np.stack([sequence(f, 1)[0].image for f in fields])).permute(0, 3, 1, 2).contiguous()
    ref = torchrow.CropRowDetector(small)(x)
    lab = lab_table_torch("cpu")[torch.from_numpy(pack_rgb(ref.veg_color.numpy()))]
    module = static.StaticDetector(240, 320, small)
    seen = []
    fit = module.band_points

    def band_points(veg, *args, **kw):  # the vegetation the band points see, to check the tier
        seen.append(int(veg.flatten(1).sum(1).max()))
        return fit(veg, *args, **kw)

    module.band_points = band_points
    if band_tier == "short":  # the short form covers exactly the largest vegetation count
        module(x, lab)
        module.band_tier = seen[0]
    elif band_tier == "whole":  # one entry short: the whole list
        module(x, lab)
        module.band_tier = seen[0] - 1
    with torch.no_grad():
        o = dict(zip(static.GRAPH_OUTPUTS, module(x, lab)))
    rows = static.finish_rows(o, 240, 320, small)
    assert torch.equal(o["hough_theta"], ref.hough_theta) and torch.equal(o["hough_rho"], ref.hough_rho)
    assert torch.equal(rows.valid, ref.row_valid) and torch.equal(rows.reason, ref.row_reason)
    assert torch.allclose(rows.a, ref.row_a, rtol=0, atol=1e-12, equal_nan=True)
    assert torch.allclose(rows.b, ref.row_b, rtol=0, atol=1e-9, equal_nan=True)
    assert bool(ref.row_valid.any())


@pytest.mark.parametrize("track", [False, True])
def test_static_band_points_equal_eager(track: bool) -> None:
    """The exported band points (static P, the short or the whole vegetation list) keep the
    eager fit's pixels exactly, around Hough lines and around tracked rows, with and without
    subsampling (step 7.2)."""
    h, w = 120, 160
    g = torch.Generator().manual_seed(3)
    veg = torch.rand((3, h, w), generator=g) < torch.tensor([0.02, 0.1, 0.45]).view(3, 1, 1)
    theta = torch.randint(0, P.n_theta, (3, 5), generator=g)
    rho = torch.randint(-60, 150, (3, 5), generator=g)
    band = torch.tensor([4, 10, 24])
    tr = ((torch.rand((3, 5), generator=g, dtype=torch.float64) - 0.5) * 0.6,
          torch.rand((3, 5), generator=g, dtype=torch.float64) * w) if track else None
    ref = fransac._band_points(veg, theta, rho, band, P, tr)
    assert bool((ref.n + ref.n // 2 > P.ransac_max_points).any()) and int((ref.n_keep > 0).sum()) >= 8
    module = static.StaticDetector(h, w, P)
    most = int(veg.flatten(1).sum(1).max())
    for tier in (most, most - 1, h * w):  # the short list, the whole list, no choice
        module.band_tier = tier
        got = module.band_points(veg, theta, rho, band, tr)
        for f in ("n", "n_keep", "v_keep"):
            assert torch.equal(getattr(got, f), getattr(ref, f)), (tier, f)
        kept = torch.arange(ref.px.shape[2]) < ref.n_keep.unsqueeze(2)
        assert torch.equal(got.px[..., :ref.px.shape[2]][kept], ref.px[kept]), tier
        assert torch.equal(got.py[..., :ref.py.shape[2]][kept], ref.py[kept]), tier


def test_static_adaptive_k_equals_eager() -> None:
    """Comparison-counted fractions (no histogram) give the eager k and raw mask, and frame 0's
    info0 equals init_state's."""
    seq = sequence(FieldSpec.at_size(160, 90, n_rows=5, seed=6), 3, drift_px_per_frame=2.0)
    x = torch.from_numpy(np.stack([f.image for f in seq])).permute(0, 3, 1, 2).contiguous()
    pv = Params(video_width=160)
    from torchrow.functional import tracking as ftrack

    st0 = ftrack.init_state(x[:1].expand(3, -1, -1, -1).contiguous(), pv)
    info0 = st0.info0 * torch.tensor([1.0, 0.3, 3.0], dtype=torch.float64)  # grow, shrink and stay
    k_e, raw_e = fveg.adapt_k(x, st0.veg_color, st0.sky, info0, pv)
    table = fveg.min_k_table(st0.veg_color, pv)
    start = torch.tensor([True, False, False])
    veg_e, bushy_e = ftrack.finish_segment(raw_e, st0.sky, pv)
    for scatter_free in (False, True):  # the histogram and the comparison counts
        step = static.StaticTrackerStep(90, 160, pv, scatter_free=scatter_free)
        veg, k_s, bushy, info_s = step.segment(x, table, st0.sky, info0, start)
        assert torch.equal(k_s, k_e) and len(set(k_e.tolist())) > 1
        assert torch.equal(info_s[0], st0.info0[0]) and torch.equal(info_s[1:], info0[1:])
        assert torch.equal(veg, veg_e) and torch.equal(bushy, bushy_e)


@pytest.mark.slow
@pytest.mark.parametrize("control_flow", [True, False])
def test_static_tracker_step_equals_tracker(control_flow: bool) -> None:
    """StaticTrackerStep == torchrow.Tracker, with branches skipped (eagerly: the ``If``'s
    choice) or always run and masked."""
    pv = Params(video_width=160, n_rows=3, max_outliers=2)
    seqs = [sequence(FieldSpec.at_size(320, 180, n_rows=5, seed=s), 7, drift_px_per_frame=1.5, gap=(2, 4))
            for s in (3, 9)]
    from torchrow.core.io import resize_to_width

    module = static.StaticTrackerStep(90, 160, pv, control_flow=control_flow)
    eager = torchrow.Tracker(pv, workers=1)
    st_e = None
    st_g = TrackerState.empty(2, pv)
    for t in range(7):
        x = torch.from_numpy(np.stack([resize_to_width(s[t].image, 160) for s in seqs])).permute(0, 3, 1, 2)
        x = x.contiguous()
        step_e, st_e = eager(x, st_e)
        table = fveg.min_k_table(st_e.veg_color, pv)
        st_g.sky = torch.where(st_g.ready, st_g.sky, fsky.sky_row(x, pv))  # the host's part of frame 0
        with torch.no_grad():
            out = module(x, table, torch.ones(2, dtype=torch.bool), *[getattr(st_g, f) for f in static.TRACKER_STATE])
        o = dict(zip(static.TRACKER_OUTPUTS, out))
        step_g = ftrack_step(o, step_e.active)
        st_g = TrackerState(veg_color=st_e.veg_color, **{f: o["next_" + f] for f in static.TRACKER_STATE})
        assert not step_differences(step_e, step_g), (t, step_differences(step_e, step_g))
        assert not step_differences(st_e, st_g), (t, step_differences(st_e, st_g))


def ftrack_step(o: dict, active: torch.Tensor):
    from torchrow.functional.tracking import TrackStep

    return TrackStep(**{f: o[f] for f in static.TRACKER_STEP}, active=active)


@pytest.mark.parametrize(("scatter_free", "flow", "tier"), [(False, "always", None), (False, "sync", 2000),
                                                      (False, "sync", 100000),
                                                      # the scatter-free re-vote (12 s) is checked with its export
                                                      pytest.param(True, "sync", None, marks=pytest.mark.heavy)])
def test_static_voter_line_search_equals_eager(scatter_free: bool, flow: str, tier: int | None) -> None:
    """find_lines with the static voter (one vote, band-only updates in chunks, or the
    scatter-free re-vote) == the eager voter, on adversarial masks that exhaust lines, drop
    outliers and restart; the static voter's chunks are small so several are skipped or run,
    and a small erase tier makes batches take the short and the whole-list erase."""
    h, w = 240, 320
    masks = torch.from_numpy(np.stack([m[:h, :w] for m in _adversarial_masks()]))
    counts = masks.flatten(1).sum(1)
    batches = [masks]
    if tier == 2000:  # a batch that fits the tier (the short erase) and one that does not
        assert bool((counts <= tier).sum() >= 2) and bool((counts > tier).any()), counts.tolist()
        batches.append(masks[counts <= tier])
    voter = fhough.StaticVoter(h, w, P, flow=flow, scatter_free=scatter_free, chunk=1000, tier=tier)
    for batch in batches:
        ref = fvan.find_lines(batch, P)
        got = fvan.find_lines(batch, P, voter, flow)
        for f in ("theta", "rho", "weight", "out_theta", "out_rho", "out_weight"):
            valid = ref.valid if not f.startswith("out") else ref.out_valid
            assert torch.equal(torch.where(valid, getattr(got, f), 0), torch.where(valid, getattr(ref, f), 0)), f
        for f in ("valid", "out_valid", "n_rows", "has_vp"):
            assert torch.equal(getattr(got, f), getattr(ref, f)), f
        assert torch.equal(got.vp, ref.vp)
    assert bool(ref.out_valid.any()) and bool((ref.n_rows < P.n_rows).any())


def test_erase_bound_holds() -> None:
    """No line of a pickable angle has more pixels within hough_band/2 than erase_bound."""
    h, w = 90, 160
    bound = fhough.erase_bound(h, w, P)
    ys, xs = np.divmod(np.arange(h * w), w)
    c, s = fhough.trig(P, torch.device("cpu"))
    half = P.hough_band_px(w) / 2
    most = 0
    for j in fhough.pickable_angles(P):
        p = xs * float(c[j]) + ys * float(s[j])
        for r in range(-fhough.rho_offset(h, w), fhough.rho_offset(h, w) + 1):
            most = max(most, int((np.abs(p - r) <= half).sum()))
    assert most <= bound <= most + 2


@settings(deadline=None, max_examples=30)
@given(max_points=st.integers(1, 900), frac=st.floats(0.0, 1.0))
def test_max_kept_bounds_every_band(max_points: int, frac: float) -> None:
    """The static number of RANSAC points equals the most any band size keeps (step 7.2)."""
    p = Params(ransac_max_points=max_points, ransac_subsample=max(1, int(frac * max_points)))
    n = np.arange(0, 4 * max_points + 10)
    v = n // 2
    kept = np.where(n + v > p.ransac_max_points, (p.ransac_subsample * n) // np.maximum(n + v, 1), n)
    assert fransac.max_kept(p) == int(kept.max())
