"""Levenberg-Marquardt through a fast renderer, corrected by the reference's defect (``fit_material.py``'s solver).

A homogeneous material has a handful of parameters (per channel :math:`\\log\\sigma_{tr}` and
:math:`\\log(\\sigma_s'/\\sigma_a)`, optionally :math:`\\log\\eta`) and the images have tens of thousands of
pixels: a least-squares problem that a Gauss-Newton method solves in a few iterations where Adam crawls along the
valley between the parameters for hundreds of steps. Two pieces:

**Levenberg-Marquardt** (inner loop). The residual of view :math:`v` is
:math:`r_v = (L_v(p) + D_v - L^*_v) / (\\lVert L^*_v\\rVert \\sqrt{V})`, so that :math:`\\sum r^2` is the mean
over the views of :func:`~fit_material.view_loss` (:math:`D_v` is the correction below, 0 without one). The
gradient :math:`g = 2 J^T r` comes from autograd through the fast renderer; the Gauss-Newton matrix
:math:`J^T J` from central differences of the renders (no autograd), with one pair of renders per *parameter group*
rather than per parameter: the renderer's channels are independent (channel c's pixels depend on channel c's
coefficients only, once the renderer's knobs are fixed), so perturbing a per-channel group in every channel at
once and keeping each channel's pixels gives all C columns of that group (tested against one column at a time). The
step solves :math:`(J^T J + \\lambda\\,\\mathrm{diag}(J^T J))\\,\\delta = -g/2`, capped at 1 in log space (a factor
e), and is taken when it lowers the loss (then :math:`\\lambda` shrinks 3x), else :math:`\\lambda` grows 4x and the
step is solved again.

**Defect correction** (outer loop, "output space mapping"). The fast renderer is not the reference: at the true
material splat is 1-7% off per channel, and a coefficient whose 10% change moves its images by less than that
(potato's red :math:`\\sigma_a`) gets fitted to the renderer's error instead. Each outer iteration rebuilds the
fast renderer at the current parameters (its knobs, e.g. splat's :math:`r_{max}`, follow the material), renders
the reference there once (forward only: the fused all-pairs kernel) and sets :math:`D_v = L^{ref}_v(p_k) -
L_v(p_k)`; the inner loop then fits :math:`L(p) + D` to the targets. At a fixed point :math:`p^*` the model equals
the reference, :math:`L(p^*) + D = L^{ref}(p^*)`, and the gradient through the fast renderer of
:math:`\\lVert L^{ref}(p^*) - L^*\\rVert^2` vanishes: when the targets are a reference render of some material,
:math:`p^*` is that material up to the reference's own discretisation error, whatever the fast method's error.
The outer loop stops when an outer iteration moves no parameter by more than ``tol`` (relative).
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Callable, Sequence

import torch
from torch import Tensor

import torchsss

__all__ = ["fd_jacobian", "fit_lm", "group_columns"]


def _flat(groups: Sequence[Tensor]) -> Tensor:
    return torch.cat([g.detach().reshape(-1) for g in groups]).double()


def _assign(groups: Sequence[Tensor], p: Tensor) -> None:
    with torch.no_grad():
        i = 0
        for g in groups:
            n = g.numel()
            g.copy_(p[i:i + n].reshape(g.shape).to(g.dtype))
            i += n


def group_columns(delta: Tensor, per_channel: bool, channels: int) -> list[Tensor]:
    """The Jacobian columns of one parameter group from the change of every residual when the group moved.

    Args:
        delta: :math:`(V, C, P)` change of the residuals (views, channels, pixels) per unit change of every entry of
            the group at once.
        per_channel: the group has one entry per channel, and channel c's residuals depend only on entry c.
        channels: C.

    Returns:
        C columns :math:`(V C P,)` (``delta`` with the other channels zeroed) when ``per_channel``, else the one
        column ``delta`` flattened.
    """
    if not per_channel:
        return [delta.reshape(-1)]
    cols = []
    for c in range(channels):
        col = torch.zeros_like(delta)
        col[:, c] = delta[:, c]
        cols.append(col.reshape(-1))
    return cols


def fd_jacobian(residual: Callable[[], Tensor], groups: Sequence[Tensor], per_channel: Sequence[bool],
                step: float = 1e-2) -> Tensor:
    """Central-difference Jacobian of ``residual()`` :math:`(V, C, P)` w.r.t. the groups, 2 evaluations a group.

    Returns:
        :math:`(V C P, n)` float64, n = the total number of entries of the groups, in their order.
    """
    p0 = _flat(groups)
    cols: list[Tensor] = []
    i = 0
    for g, pc in zip(groups, per_channel):
        n = g.numel()
        e = torch.zeros_like(p0)
        e[i:i + n] = step
        _assign(groups, p0 + e)
        r_plus = residual().double()
        _assign(groups, p0 - e)
        r_minus = residual().double()
        _assign(groups, p0)
        c = (r_plus - r_minus) / (2.0 * step)
        got = group_columns(c, pc, c.shape[1])
        if len(got) != n:
            raise ValueError(f"groups: a per-channel group needs one entry per channel ({c.shape[1]}), got {n}")
        cols += got
        i += n
    return torch.stack(cols, dim=1)


def fit_lm(make_renderer: Callable[[], object], lights, cameras, targets: Sequence[Tensor], groups: Sequence[Tensor],
           per_channel: Sequence[bool], *, correct: Callable[[], list[Tensor]] | None = None,
           record: Callable[[], dict] | None = None, outer: int = 8, inner: int = 8, tol: float = 1e-3,
           rtol: float = 1e-3, fd_step: float = 1e-2, max_log_step: float = 1.0, rebuild_after: float = 1.0,
           progress: bool = True) -> dict:
    """Levenberg-Marquardt on ``groups`` through ``make_renderer()``, with the reference defect of ``correct``.

    Args:
        make_renderer: builds the fast differentiable renderer from the current parameters (called once per outer
            iteration, so that knobs planned from the material follow it).
        lights: the scene's lights.
        cameras: one camera per view.
        targets: one :math:`(1, C, H, W)` image per view.
        groups: the optimised tensors (e.g. ``material.log_sigma_tr``), updated in place.
        per_channel: per group, whether entry c acts on channel c alone (see :func:`group_columns`).
        correct: returns the reference images at the current parameters (one per view); None: no correction.
        record: returns the parameters to store in the trace (default: the groups as lists).
        outer: outer (defect-correction) iterations at most.
        inner: LM iterations per outer iteration at most.
        tol: convergence: an LM step, or an outer iteration, that moves every parameter by less than this (in log
            space: relative) ends the inner, or the outer, loop.
        rtol: an LM step that lowers the loss by less than this fraction ends the inner loop, and an outer
            iteration whose reference loss is not lower than the previous one's by this fraction ends the fit (a
            direction the images do not determine, e.g. ketchup's blue albedo, would otherwise drift for ever).
        fd_step: central-difference step of the Gauss-Newton matrix (log space).
        max_log_step: largest change of any parameter in one step.
        rebuild_after: end the inner loop once a parameter moved by more than this (log space) in this outer
            iteration: the renderer's knobs, planned for the parameters at its build, and the correction, measured
            there, go stale far from them.
        progress: a tqdm progress bar over the LM iterations.

    Returns:
        ``{"loss": [...], "trace": [...], "outer": [...], "renderer": the last renderer, "renders": n}``: the
        model loss before every LM iteration and after the last; per LM iteration the recorded parameters, the
        loss, :math:`\\lambda`, the outer index and the wall time; per outer iteration the reference loss at its
        start (``correct``'s images against the targets: the fit's honest measure) and the largest parameter
        change; ``"reference_loss"``: the reference loss of the returned parameters (those of the final or of an
        earlier outer iteration, whichever the reference found better; None without ``correct``).
    """
    if len(cameras) != len(targets) or not cameras:
        raise ValueError(f"targets: expected one image per camera ({len(cameras)}), got {len(targets)}")
    if len(groups) != len(per_channel):
        raise ValueError(f"per_channel: expected one flag per group ({len(groups)}), got {len(per_channel)}")
    record = record or (lambda: {f"p{i}": g.detach().reshape(-1).tolist() for i, g in enumerate(groups)})
    views = len(cameras)
    scale = [1.0 / (float(t.norm()) * math.sqrt(views) + 1e-30) for t in targets]
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=outer * inner, desc="fit (LM)", unit="it", file=sys.stdout)
    t0 = time.perf_counter()
    losses: list[float] = []
    trace: list[dict] = []
    outers: list[dict] = []
    renders = 0
    renderer = None

    def residual(offsets: list[Tensor]) -> Tensor:
        nonlocal renders
        rs = []
        for cam, t, off, s in zip(cameras, targets, offsets, scale):
            img = renderer.render(lights, cam).radiance
            rs.append(((img + off - t) * s).reshape(t.shape[1], -1))
        renders += views
        return torch.stack(rs)  # (V, C, P)

    with torchsss.validation(False):
        for k in range(outer):
            renderer = make_renderer()
            p_start = _flat(groups)
            with torch.no_grad():
                fast = [renderer.render(lights, c).radiance for c in cameras]
                renders += views
                if correct is not None:
                    ref = correct()
                    offsets = [r - f for r, f in zip(ref, fast)]
                    ref_loss = sum(float(((r - t) ** 2).sum() / (t**2).sum()) for r, t in zip(ref, targets)) / views
                else:
                    offsets = [torch.zeros_like(t) for t in targets]
                    ref_loss = None
            lam = 1e-3
            r = residual(offsets)
            loss = (r**2).sum()
            done_inner = 0
            for _ in range(inner):
                for g in groups:
                    g.grad = None
                loss.backward()
                grad = torch.cat([(g.grad if g.grad is not None else torch.zeros_like(g)).reshape(-1)
                                  for g in groups]).double()
                with torch.no_grad():
                    jac = fd_jacobian(lambda: residual(offsets), groups, per_channel, fd_step)  # noqa: B023
                    a = jac.T @ jac
                    p = _flat(groups)
                    current = float(loss.detach())
                    losses.append(current)
                    accepted = False
                    for _retry in range(8):
                        m = a + lam * torch.diag(torch.diag(a)) + 1e-12 * torch.eye(len(p), dtype=a.dtype)
                        delta = torch.linalg.solve(m, -0.5 * grad)
                        big = float(delta.abs().max())
                        if big > max_log_step:
                            delta = delta * (max_log_step / big)
                        _assign(groups, p + delta)
                        with torch.enable_grad():
                            r_try = residual(offsets)
                            loss_try = (r_try**2).sum()
                        if float(loss_try.detach()) < current:
                            accepted, lam = True, max(lam / 3.0, 1e-9)
                            break
                        lam *= 4.0
                    if not accepted:
                        _assign(groups, p)
                done_inner += 1
                trace.append({**record(), "loss": current, "lambda": lam, "outer": k,
                              "t_s": time.perf_counter() - t0})
                if bar is not None:
                    bar.update(1)
                    bar.set_postfix(loss=f"{current:.3e}", outer=k)
                if not accepted:
                    break
                gain = (current - float(loss_try.detach())) / current
                loss = loss_try
                if float(delta.abs().max()) < tol or gain < rtol:
                    break
                if float((_flat(groups) - p_start).abs().max()) > rebuild_after:
                    break
            if bar is not None:
                bar.update(inner - done_inner)
            moved = float((_flat(groups) - p_start).abs().max())
            outers.append({"outer": k, "reference_loss": ref_loss, "p": p_start, "model_loss_end": float(loss.detach()),
                           "lm_iterations": done_inner, "max_change": moved, "t_s": time.perf_counter() - t0})
            if moved < tol:
                break
            if ref_loss is not None and len(outers) > 1 and outers[-2]["reference_loss"] is not None \
                    and ref_loss > (1.0 - rtol) * outers[-2]["reference_loss"]:
                break
        losses.append(float(loss.detach()))
        final_ref = None
        if correct is not None:  # the reference at the end; the best parameters the reference has seen are kept
            with torch.no_grad():
                ref = correct()
            final_ref = sum(float(((r - t) ** 2).sum() / (t**2).sum()) for r, t in zip(ref, targets)) / views
            seen = [(o["reference_loss"], o["p"]) for o in outers]
            best_loss, best_p = min(seen, key=lambda x: x[0])
            if best_loss < final_ref:
                _assign(groups, best_p)
                final_ref = best_loss
    for o in outers:
        o.pop("p")
    if bar is not None:
        bar.close()
    return {"loss": losses, "trace": trace, "outer": outers, "renderer": renderer, "renders": renders,
            "reference_loss": final_ref}
