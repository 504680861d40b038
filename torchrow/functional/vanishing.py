"""Batched vanishing point with outlier lines and restarts (ALGORITHM.md sections 5-6).

The per-image control flow of the reference (fill N lines, solve, drop an outlier, refill,
restart with N-1 after ``max_outliers`` drops) runs as a state machine: at every step each
unfinished image either extracts one Hough line or checks its vanishing point. The number of
steps has a static bound; the loop stops early once every image is finished.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, NamedTuple

import torch

from torchrow.core.params import Params
from torchrow.functional import _exact
from torchrow.functional._flow import branch, check_flow, keep, repeat
from torchrow.functional.hough import EagerVoter, StaticVoter, Voter, excluded_angles, peak, trig

__all__ = ["VPSolution", "vanishing_point", "LineSearch", "LineCarry", "find_lines", "max_steps"]


@dataclass
class VPSolution:
    """Batched weighted least-squares intersection; all ``(B,)`` except ``residuals`` ``(B, S)``."""

    x: torch.Tensor  # float64
    y: torch.Tensor  # float64
    ok: torch.Tensor  # bool: >= 2 lines and a regular system
    residuals: torch.Tensor  # float64 (B, S), 0 on empty slots
    spread: torch.Tensor  # float64


def vanishing_point(theta: torch.Tensor, rho: torch.Tensor, weight: torch.Tensor, valid: torch.Tensor,
                    params: Params, tables: tuple[torch.Tensor, torch.Tensor] | None = None) -> VPSolution:
    """Solve ``[[A, C], [C, B]] [x0, y0] = [D, E]`` for every image by Cramer's rule.

    Parameters
    ----------
    theta, rho, weight : int64 (B, S) held lines, compact at the front in held order.
    valid : bool (B, S) which slots hold a line.

    tables : optional ``(cos, sin)`` float64 ``(n_theta,)``, the shared tables (default
        :func:`~torchrow.functional.hough.trig`; an exported module passes its buffers).

    Sums run slot by slot in held order, as in the reference, so the bits agree: the terms
    of all slots are computed at once (the same products, ``(w*c)*c`` and so on), and only
    the six running sums step through the slots, as one ``(B, 6)`` tensor (a few ops per slot:
    an exported line-search step holds this once per step).
    """
    cos, sin = tables if tables is not None else trig(params, theta.device)
    co, si = cos[theta], sin[theta]
    w, r = weight.to(torch.float64), rho.to(torch.float64)
    z = torch.zeros(theta.shape[0], dtype=torch.float64, device=theta.device)
    wc, ws, wr = w * co, w * si, w * r
    terms = torch.stack([wc * co, ws * si, ws * co, wr * co, wr * si, w], dim=2)  # (B, S, 6)
    acc = torch.zeros((theta.shape[0], 6), dtype=torch.float64, device=theta.device)
    for k in range(theta.shape[1]):
        acc = torch.where(valid[:, k:k + 1], acc + terms[:, k], acc)
    a, b, c, d, e, wsum = acc.unbind(1)
    det = a * b - c * c
    trace = a + b
    ok = (valid.sum(dim=1) >= 2) & ~(det.abs() < params.singular_tol * trace * trace)
    safe = torch.where(ok, det, torch.ones_like(det))
    x0 = torch.where(ok, (d * b - c * e) / safe, z)
    y0 = torch.where(ok, (a * e - c * d) / safe, z)
    res = torch.where(valid, r - x0.unsqueeze(1) * co - y0.unsqueeze(1) * si, torch.zeros_like(r))
    safe_w = torch.where(wsum > 0, wsum, torch.ones_like(wsum))
    parts = (w / safe_w.unsqueeze(1)) * (res * res)
    s2 = z
    for k in range(theta.shape[1]):
        s2 = torch.where(valid[:, k], s2 + parts[:, k], s2)
    return VPSolution(x0, y0, ok, res, _exact.sqrt(s2))


@dataclass
class LineSearch:
    """Outcome of sections 5-6 for a batch.

    ``theta``/``rho``/``weight`` int64 ``(B, n_rows)`` held lines (compact, ``valid`` marks
    them); ``out_*`` int64 ``(B, O)`` dropped outliers in drop order (``out_valid``);
    ``n_rows`` int64 ``(B,)``; ``vp`` float64 ``(B, 2)`` with ``has_vp`` bool ``(B,)``.
    """

    theta: torch.Tensor
    rho: torch.Tensor
    weight: torch.Tensor
    valid: torch.Tensor
    out_theta: torch.Tensor
    out_rho: torch.Tensor
    out_weight: torch.Tensor
    out_valid: torch.Tensor
    n_rows: torch.Tensor
    vp: torch.Tensor
    has_vp: torch.Tensor


class LineCarry(NamedTuple):
    """The loop state of :func:`find_lines`, per image: held lines ``theta``/``rho``/``weight``
    int64 ``(B, S)`` (compact; ``held`` int64 ``(B,)`` of them), dropped outliers ``out`` int64
    ``(B, O, 3)`` (theta, rho, weight in drop order; ``n_out`` of them), ``n`` the lines
    sought (N), ``dropped`` outliers since the last restart, ``done`` bool, ``vp`` float64
    ``(B, 2)`` with ``has_vp`` bool. A loop carries it flat, followed by the voter's state."""

    theta: torch.Tensor
    rho: torch.Tensor
    weight: torch.Tensor
    held: torch.Tensor
    out: torch.Tensor
    n_out: torch.Tensor
    n: torch.Tensor
    dropped: torch.Tensor
    done: torch.Tensor
    vp: torch.Tensor
    has_vp: torch.Tensor

    @classmethod
    def split(cls, flat: tuple) -> tuple[LineCarry, tuple]:
        """A flat loop carry as this state and the voter's state after it."""
        k = len(cls._fields)
        return cls(*flat[:k]), tuple(flat[k:])


def max_steps(params: Params) -> int:
    """Static bound on state-machine steps: for each N, N fills, then per outlier one check
    and one refill, then a final check."""
    return sum(n + 2 * params.max_outliers + 1 for n in range(2, params.n_rows + 1)) + 1


def _drop(t: torch.Tensor, i: torch.Tensor, which: torch.Tensor) -> torch.Tensor:
    """Remove slot ``i`` (B,) from ``t`` (B, S) where ``which``; later slots move up one."""
    s = t.shape[1]
    k = torch.arange(s, device=t.device).unsqueeze(0)
    src = (k + (k >= i.unsqueeze(1)).to(k.dtype)).clamp(max=s - 1)
    return torch.where(which.unsqueeze(1), torch.gather(t, 1, src), t)


def outlier_check(theta: torch.Tensor, rho: torch.Tensor, weight: torch.Tensor, valid: torch.Tensor,
                  check: torch.Tensor, params: Params, tables: tuple[torch.Tensor, torch.Tensor] | None = None):
    """Section 6 for the images where ``check`` (bool ``(B,)``): the VP of the held lines
    (int64 ``(B, S)``, ``valid`` bool ``(B, S)``) and its worst line.

    Returns ``no_vp``, ``finish`` (converged: no outlier) and ``drop`` (line ``i`` is an
    outlier), bool ``(B,)`` each, ``i`` int64 ``(B,)`` and the VP ``xy`` float64 ``(B, 2)``.
    """
    sol = vanishing_point(theta, rho, weight, valid, params, tables)
    err = torch.where(valid, sol.residuals.abs(), torch.full_like(sol.residuals, -1.0))
    i = torch.argmax(err, dim=1)  # first on ties
    e_i = err.gather(1, i.unsqueeze(1)).squeeze(1)
    is_out = (e_i > params.outlier_ratio * sol.spread) & (e_i > params.outlier_min_px)
    return check & ~sol.ok, check & sol.ok & ~is_out, check & sol.ok & is_out, i, torch.stack([sol.x, sol.y], 1)


def drop_outlier(theta, rho, weight, i, drop, out, n_out):
    """Where ``drop``: record line ``i`` as the next outlier (``out`` int64 ``(B, O, 3)``,
    ``n_out`` ``(B,)``) and remove it from the held lines, later lines moving up one."""
    rec = torch.stack([t.gather(1, i.unsqueeze(1)).squeeze(1) for t in (theta, rho, weight)], 1)
    o_slot = (torch.arange(out.shape[1], device=out.device).unsqueeze(0) == n_out.unsqueeze(1)) & drop.unsqueeze(1)
    out = torch.where(o_slot.unsqueeze(-1), rec.unsqueeze(1), out)
    return (_drop(theta, i, drop), _drop(rho, i, drop), _drop(weight, i, drop), out,
            n_out + drop.to(torch.int64))


def find_lines(hough_in: torch.Tensor, params: Params, voter: Voter | None = None, flow: str = "sync") -> LineSearch:
    """N-maximum extraction with outlier rejection and N-1 restarts, for every image at once.

    The one state machine of sections 5-6, for the eager detector and tracker and for the
    exportable graphs: ``voter`` says how votes are kept (a :class:`~.hough.Voter`:
    :class:`~.hough.EagerVoter`, the default, or :class:`~.hough.StaticVoter`), ``flow`` how finished work is skipped
    (:mod:`._flow`): ``"sync"`` stops once every image is finished (host sync), ``"cond"``
    puts each of the :func:`max_steps` steps in a ``torch.cond`` on "some image is not
    finished" (an exported graph keeps the static bound and exits early at run time),
    ``"loop"`` is one ``while_loop`` over the steps (an ONNX ``Loop`` whose body is stored
    once, stopping when every image is finished), ``"always"`` runs every step with masks.

    Parameters
    ----------
    hough_in : bool (B, H, W) Hough input (section 4).

    Memory: the voter's (eager: the accumulator and a copy of it, int32 ``(B, n_theta, 2D+1)``
    each, about 37 MB each at B = 64, 320x240, plus the voting temporaries of :mod:`.hough`).
    """
    check_flow(flow)
    voter = voter if voter is not None else EagerVoter(params)
    dev = hough_in.device
    bsz = hough_in.shape[0]
    s_max = params.n_rows
    o_max = max(params.n_rows - 1, 1) * params.max_outliers
    vstate, init = voter.start(hough_in)
    tables = (voter.cos, voter.sin) if isinstance(voter, StaticVoter) else None
    i64: dict[str, Any] = dict(dtype=torch.int64, device=dev)
    # an image without Hough pixels ends as its first extraction would leave it (N = 0, no
    # VP): done before the first step, so a search of only such images runs no step at all
    n = torch.where(hough_in.flatten(1).any(dim=1), params.n_rows, 0).to(torch.int64)
    carry = LineCarry(theta=torch.zeros((bsz, s_max), **i64), rho=torch.zeros((bsz, s_max), **i64),
                      weight=torch.zeros((bsz, s_max), **i64), held=torch.zeros(bsz, **i64),
                      out=torch.zeros((bsz, o_max, 3), **i64), n_out=torch.zeros(bsz, **i64), n=n,
                      dropped=torch.zeros(bsz, **i64), done=n < 2,
                      vp=torch.zeros((bsz, 2), dtype=torch.float64, device=dev),
                      has_vp=torch.zeros(bsz, dtype=torch.bool, device=dev))
    # a loop's carry may not alias what its body reads besides (the restart state ``init``)
    vstate = tuple(v.clone() if isinstance(v, torch.Tensor) and flow == "loop" else v for v in vstate)
    slots = torch.arange(s_max, device=dev).unsqueeze(0)

    def step(*flat):
        c, vs = LineCarry.split(flat)
        valid = slots < c.held.unsqueeze(1)
        fill = ~c.done & (c.held < c.n)
        check = ~c.done & ~fill

        # --- fill: extract one line ------------------------------------------------------------
        def extract(theta, rho, weight, held, n, *vs):
            th, r_idx, w = peak(voter.votes(vs), excluded_angles(theta, valid, params), voter.angles)
            got = fill & (w > 0)
            n = torch.where(fill & (w == 0), held, n)  # extraction ran dry: N becomes the count
            put = got.unsqueeze(1) & (slots == held.unsqueeze(1))
            rho_new = r_idx - voter.d
            theta = torch.where(put, th.unsqueeze(1), theta)
            rho = torch.where(put, rho_new.unsqueeze(1), rho)
            weight = torch.where(put, w.unsqueeze(1), weight)
            held = held + got.to(torch.int64)
            return (theta, rho, weight, held, n) + tuple(voter.erase(vs, init, th, rho_new, got))

        # --- check: vanishing point and outlier ------------------------------------------------
        def verify(*carry):
            theta, rho, weight, held, out, n_out, n, dropped, done, vp, has_vp = carry
            no_vp, finish, drop, i, xy = outlier_check(theta, rho, weight, valid, check, params, tables)
            vp = torch.where(finish.unsqueeze(1), xy, vp)
            has_vp = has_vp | finish
            theta, rho, weight, out, n_out = drop_outlier(theta, rho, weight, i, drop, out, n_out)
            held = held - drop.to(torch.int64)
            dropped = dropped + drop.to(torch.int64)
            restart = drop & (dropped == params.max_outliers)
            n = n - restart.to(torch.int64)
            held = torch.where(restart, torch.zeros_like(held), held)
            dropped = torch.where(restart, torch.zeros_like(dropped), dropped)
            done = done | no_vp | finish | (restart & (n < 2))
            return LineCarry(theta, rho, weight, held, out, n_out, n, dropped, done, vp, has_vp) + (restart,)

        def unchecked(*carry):
            return keep(*carry) + (torch.zeros_like(c.done),)

        # each part runs only when some image needs it (at B = 1 a step is a fill or a check):
        # eagerly a host check, in an exported graph an If (flow "always": both, masked)
        filled = (c.theta, c.rho, c.weight, c.held, c.n, *vs)
        if flow == "sync":  # the eager voter's state is not a tuple of tensors
            if bool(fill.any()):
                filled = extract(*filled)
        else:
            filled = branch(flow, fill.any(), extract, keep, filled)
        theta, rho, weight, held, n, *rest = filled
        vs = tuple(rest)
        c = c._replace(theta=theta, rho=rho, weight=weight, held=held, n=n)
        *checked, restart = branch(flow, check.any(), verify, unchecked, tuple(c))
        vs = voter.reset(tuple(vs), init, restart)
        return tuple(checked) + tuple(vs)

    # early exit once every image is done; the bound is what an exported graph keeps
    flat = repeat(flow, max_steps(params), lambda *f: LineCarry.split(f)[0].done.all(), step, carry + vstate)

    c = LineCarry.split(flat)[0]
    out_valid = torch.arange(o_max, device=dev).unsqueeze(0) < c.n_out.unsqueeze(1)
    return LineSearch(theta=c.theta, rho=c.rho, weight=c.weight, valid=slots < c.held.unsqueeze(1),
                      out_theta=c.out[..., 0], out_rho=c.out[..., 1], out_weight=c.out[..., 2], out_valid=out_valid,
                      n_rows=c.n, vp=c.vp, has_vp=c.has_vp)
