"""Many small independent least-squares problems at once: Levenberg-Marquardt per pixel (torch, any device).

Once the lights are fixed every pixel of the fit is its own problem in a handful of parameters (normal gradient,
base colour, roughness, metallic: 7). :func:`levenberg_marquardt` solves N of them together: a Gauss-Newton
system per pixel with the Cauchy loss's iteratively reweighted least-squares weights (given in closed form by the
caller, or from forward-mode automatic differentiation, a tangent per parameter, all in one vectorised
``torch.func.jvp``), its damping adapted per pixel (a step is kept only where it lowers that pixel's loss), and
the P x P systems solved by :func:`cholesky_solve`, written out elementwise over the pixels so that the result
does not depend on how a BLAS splits the work (the fit must be bit-for-bit repeatable for a seed).

A second-order solve: on glossy surfaces a first-order one (Adam) needs about ten times the iterations and
still stops short of the minimum (tests/test_refine_solve.py).
"""
from __future__ import annotations

import math
from typing import Callable

import torch


def cholesky_solve(h: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
    """Solve ``h x = g`` for every row: h (N, P, P) symmetric positive definite, g (N, P) -> x (N, P), or g
    (N, P, R) (R right-hand sides) -> x (N, P, R).

    Elementwise over N (no batched LAPACK call), so the result is the same whatever the batch size or alignment.
    Pivots are clamped at 1e-12 (a semi-definite ``h`` gives a finite answer).
    """
    if h.ndim != 3 or h.shape[1] != h.shape[2] or g.shape[:2] != h.shape[:2] or g.ndim not in (2, 3):
        raise ValueError(f"h must be (N, P, P) and g (N, P) or (N, P, R), got {tuple(h.shape)} and {tuple(g.shape)}")
    if g.ndim == 3:
        h = h[..., None]  # each pivot broadcasts over the right-hand sides
    p = g.shape[1]
    low = [[None] * p for _ in range(p)]
    for j in range(p):
        acc = h[:, j, j]
        for k in range(j):
            acc = acc - low[j][k] * low[j][k]
        d = acc.clamp(min=1e-12).sqrt()
        low[j][j] = d
        for i in range(j + 1, p):
            acc = h[:, i, j]
            for k in range(j):
                acc = acc - low[i][k] * low[j][k]
            low[i][j] = acc / d
    y = []
    for i in range(p):
        acc = g[:, i]
        for k in range(i):
            acc = acc - low[i][k] * y[k]
        y.append(acc / low[i][i])
    x = [None] * p
    for i in reversed(range(p)):
        acc = y[i]
        for k in range(i + 1, p):
            acc = acc - low[k][i] * x[k]
        x[i] = acc / low[i][i]
    return torch.stack(x, 1)


ResidualFn = Callable[[torch.Tensor, torch.Tensor], tuple[torch.Tensor, torch.Tensor]]
SystemFn = Callable[[torch.Tensor, torch.Tensor, torch.Tensor, float], tuple[torch.Tensor, torch.Tensor]]
Shared = tuple[list[int], torch.Tensor, torch.Tensor]
LAM_DONE = 1e3  # rejected steps count toward "done" once the damping has grown to this


def robust_loss(robust: torch.Tensor, quadratic: torch.Tensor, weight: torch.Tensor, scale: float) -> torch.Tensor:
    """Per-problem loss (N,): ``weight * sum log(1 + (robust / scale)^2) + sum quadratic^2``.

    robust (N, M): residuals under the Cauchy loss; quadratic (N, Q): residuals under a plain square (priors);
    weight (N,).
    """
    return torch.log1p((robust / scale) ** 2).sum(1) * weight + (quadratic * quadratic).sum(1)


def levenberg_marquardt(residuals: ResidualFn, theta: torch.Tensor, weight: torch.Tensor, scale: float,
                        iters: int, damping: float = 1e-2, on_step: Callable[[float], None] | None = None,
                        shared: Shared | None = None, tol: float = 1e-4,
                        system: SystemFn | None = None) -> torch.Tensor:
    """Minimise :func:`robust_loss` of ``residuals(theta)`` for N independent problems of P parameters.

    residuals: (theta (n, P), rows (n,) int64) -> (robust (n, M), quadratic (n, Q)) of the problems ``rows``
    (their parameters ``theta``), row i depending on theta[i] alone;
    theta: (N, P) start; weight (N,) and scale: of the robust part. Returns theta (N, P) after ``iters``
    iterations. Each iteration: the Gauss-Newton system (``system``) with weights ``2 weight / (scale^2 + r^2)``
    (the Cauchy loss's IRLS weights, so the step is a descent direction) damped by ``lambda * diag`` (Marquardt),
    one trial step; a problem keeps the step only if its loss went down (then lambda / 3, else lambda * 4, per
    problem).
    A problem whose loss went down by at most ``tol`` of itself in two iterations in a row is done and drops out,
    so that later iterations cost only what still moves. Such an iteration is an accepted step that gained that
    little, or a rejected one where the undamped Gauss-Newton step promises that little by the quadratic model
    (half the Newton decrement squared: the problem sits at its minimum, and rounding rejected the step) or where
    lambda has grown to LAM_DONE.
    ``on_step(mean loss)`` after each iteration.

    system: (theta (n, P), rows, weight (n,), scale) -> (gradient (n, P), Gauss-Newton matrix (n, P, P)) of
    :func:`robust_loss` with those weights (:func:`_normal_equations`) at the problems ``rows``, in closed form
    from a caller that knows its model's derivatives; without it the Jacobian is forward-mode automatic
    differentiation of ``residuals`` (a tangent per parameter, all of them in one vectorised ``jvp``), where
    shared: (params, robust_owner (M,), quadratic_owner (Q,)): parameters that move disjoint residual entries
    (a colour's three channels) share one tangent; entry e's derivative is credited to ``params[owner[e]]``.
    """
    if theta.ndim != 2:
        raise ValueError(f"theta must be (N, P), got {tuple(theta.shape)}")
    n, p = theta.shape
    theta = theta.detach().clone()
    weight = weight.detach()
    dev, dt = theta.device, theta.dtype
    every = torch.arange(n, device=dev)
    c2 = scale * scale
    lam = torch.full((n,), damping, dtype=dt, device=dev)
    stalls = torch.zeros(n, dtype=torch.int64, device=dev)
    eye = torch.arange(p, device=dev)
    with torch.no_grad():
        loss = robust_loss(*residuals(theta, every), weight, scale)
    groups = [[j] for j in range(p) if shared is None or j not in shared[0]]
    if shared is not None:
        groups.append(list(shared[0]))
    active = every
    for _ in range(iters):
        if len(active) == 0:
            if on_step is not None:
                on_step(float(loss.mean()))
            continue
        th = theta[active]
        if system is not None:
            grad, hess = system(th, active, weight[active], scale)
        else:
            r, q, jr, jq = _forward_jacobian(residuals, th, active, groups, shared)
            r, q = r.detach(), q.detach()
            w = weight[active, None] * 2.0 / (c2 + r * r)  # IRLS weight: rho'(r) / r of weight * log(1 + r^2 / c^2)
            grad, hess = _normal_equations(r, q, jr, jq, w)
        diag = torch.diagonal(hess, dim1=1, dim2=2).clone()
        lam_a = lam[active]
        hess[:, eye, eye] = diag * (1.0 + lam_a[:, None]) + 1e-6
        trial = th - cholesky_solve(hess, grad)
        with torch.no_grad():
            trial_loss = robust_loss(*residuals(trial, active), weight[active], scale)
        old = loss[active]
        better = torch.isfinite(trial_loss) & (trial_loss < old)
        theta[active] = torch.where(better[:, None], trial, th)
        new = torch.where(better, trial_loss, old)
        loss[active] = new
        lam_a = torch.where(better, lam_a / 3.0, lam_a * 4.0).clamp(1e-6, 1e6)
        lam[active] = lam_a
        # done: a step that gained (almost) nothing, or a rejected one where the undamped Gauss-Newton step
        # promises nothing by the quadratic model (half the Newton decrement squared: the problem sits at its
        # minimum) or once the damping is large (a small step rejected is only a step too long)
        at_minimum = torch.zeros_like(better)
        rejected = torch.nonzero(~better).squeeze(1)
        if len(rejected):
            h_r = hess[rejected]
            h_r[:, eye, eye] = diag[rejected] + 1e-6
            g_r = grad[rejected]
            at_minimum[rejected] = 0.5 * (g_r * cholesky_solve(h_r, g_r)).sum(1) <= tol * old[rejected]
        stalled = ((old - new) <= tol * old) & (better | (lam_a >= LAM_DONE) | at_minimum)
        stalls[active] = torch.where(stalled, stalls[active] + 1, torch.zeros_like(stalls[active]))
        active = active[stalls[active] < 2]
        if on_step is not None:
            on_step(float(loss.mean()))
    return theta


def _normal_equations(r, q, jr, jq, w):
    """(gradient (n, P), Gauss-Newton matrix (n, P, P)) of :func:`robust_loss` per problem: ``w`` (n, M) the IRLS
    weights of the robust residuals ``r`` (n, M), ``q`` (n, Q) the quadratic ones, ``jr`` / ``jq`` their
    derivatives by each of the P parameters."""
    p = len(jr)
    wr = w * r
    grad = torch.stack([(wr * jr[i]).sum(1) + 2.0 * (q * jq[i]).sum(1) for i in range(p)], 1)
    hess = torch.empty((r.shape[0], p, p), dtype=r.dtype, device=r.device)
    for i in range(p):
        wj = w * jr[i]
        for j in range(i, p):
            v = (wj * jr[j]).sum(1) + 2.0 * (jq[i] * jq[j]).sum(1)
            hess[:, i, j] = v
            hess[:, j, i] = v
    return grad, hess


#: Derivatives of residuals by shared parameters, sparse: (columns (E,) int64, values (N, E)): residual entry e of
#: problem i depends on shared parameter ``columns[e]`` through ``values[i, e]``; a residual may appear in several.
Slots = list[tuple[torch.Tensor, torch.Tensor]]
JointJacobianFn = Callable[[torch.Tensor, torch.Tensor],
                           tuple[torch.Tensor, torch.Tensor, list[torch.Tensor], list[torch.Tensor], Slots, Slots]]


def joint_levenberg_marquardt(residuals: Callable[[torch.Tensor, torch.Tensor], tuple[torch.Tensor, torch.Tensor]],
                              jacobian: JointJacobianFn, theta: torch.Tensor, shared: torch.Tensor,
                              weight: torch.Tensor, scale: float, iters: int, damping: float = 1e-2,
                              tol: float = 1e-6, project: Callable[[torch.Tensor], torch.Tensor] | None = None,
                              on_step: Callable[[float], None] | None = None) -> tuple[torch.Tensor, torch.Tensor, int]:
    """Minimise the sum over N problems of :func:`robust_loss` where every problem has P parameters of its own
    (``theta`` (N, P)) and all of them share S parameters (``shared`` (S,)): a light's intensity seen by every
    pixel. Levenberg-Marquardt on the whole, its Gauss-Newton system solved through the Schur complement of the
    per-problem blocks (block-diagonal, P x P each, solved elementwise by :func:`cholesky_solve`), so a step costs
    about what N independent steps do plus an S x S solve; one damping for the whole (a step is kept where the
    total loss went down: lambda / 3, else lambda * 4).

    residuals: (theta (N, P), shared (S,)) -> (robust (N, M), quadratic (N, Q)); jacobian: the same arguments ->
    (robust, quadratic, [d robust / d theta_j] * P, [d quadratic / d theta_j] * P, robust slots, quadratic slots),
    the slots (:data:`Slots`) the derivatives by the shared parameters. weight (N,) and scale: of the robust part.
    project: maps a trial theta onto a constraint before its loss is taken (None: none). Stops after ``iters``
    iterations, or once two in a row lowered the loss by at most ``tol`` of it. Returns (theta, shared,
    iterations done)."""
    if theta.ndim != 2 or shared.ndim != 1:
        raise ValueError(f"theta must be (N, P) and shared (S,), got {tuple(theta.shape)} and {tuple(shared.shape)}")
    n, p = theta.shape
    size = shared.shape[0]
    theta, shared, weight = theta.detach().clone(), shared.detach().clone(), weight.detach()
    if project is not None:
        theta = project(theta)
    dt, dev = theta.dtype, theta.device
    c2 = scale * scale
    eye = torch.arange(p, device=dev)
    with torch.no_grad():
        loss = float(robust_loss(*residuals(theta, shared), weight, scale).sum())
    lam, stalls, done = damping, 0, 0
    for _ in range(iters):
        done += 1
        r, q, jr, jq, slots, qslots = jacobian(theta, shared)
        r, q = r.detach(), q.detach()
        w = weight[:, None] * 2.0 / (c2 + r * r)
        grad, hess = _normal_equations(r, q, jr, jq, w)
        # the shared block: its gradient, its coupling to each problem's parameters, its own matrix
        g_s = torch.zeros(size, dtype=dt, device=dev)
        cross = torch.zeros((n, p, size), dtype=dt, device=dev)
        h_s = torch.zeros((size, size), dtype=dt, device=dev)
        terms = [(slots, w, r, jr, 1.0), (qslots, None, q, jq, 2.0)]
        for sl, wt, res, jac, f in terms:
            for cols, vals in sl:
                wv = f * vals if wt is None else wt * vals
                g_s.index_add_(0, cols, (wv * res).sum(0))
                for i in range(p):
                    cross[:, i].index_add_(1, cols, wv * jac[i])
                for cols_b, vals_b in sl:  # every slot of a kind covers the same residual entries
                    h_s.index_put_((cols, cols_b), (wv * vals_b).sum(0), accumulate=True)
        diag = torch.diagonal(hess, dim1=1, dim2=2).clone()
        diag_s = torch.diagonal(h_s).clone()
        while True:
            a = hess.clone()
            a[:, eye, eye] = diag * (1.0 + lam) + 1e-6
            c = h_s.clone()
            c[range(size), range(size)] = diag_s * (1.0 + lam) + 1e-6
            x = cholesky_solve(a, torch.cat([cross, grad[..., None]], 2))  # (N, P, S + 1)
            schur = c - torch.einsum("npa,npb->ab", cross, x[..., :size])
            rhs = g_s - torch.einsum("npa,np->a", cross, x[..., size])
            d_s = torch.linalg.solve(schur.double(), rhs.double()).to(dt)
            d_t = x[..., size] - (x[..., :size] * d_s).sum(-1)
            trial, trial_s = theta - d_t, shared - d_s
            if project is not None:
                trial = project(trial)
            with torch.no_grad():
                trial_loss = float(robust_loss(*residuals(trial, trial_s), weight, scale).sum())
            if math.isfinite(trial_loss) and trial_loss < loss:
                gain = loss - trial_loss
                theta, shared, loss, lam = trial, trial_s, trial_loss, max(lam / 3.0, 1e-6)
                break
            lam = lam * 4.0
            if lam > 1e6:
                gain = 0.0
                break
        stalls = stalls + 1 if gain <= tol * loss else 0
        if on_step is not None:
            on_step(loss / n)
        if stalls >= 2 or lam > 1e6:
            break
    return theta, shared, done


def _forward_jacobian(residuals: ResidualFn, th: torch.Tensor, rows: torch.Tensor, groups: list[list[int]],
                      shared: Shared | None):
    """(robust, quadratic, [d robust / d theta_j], [d quadratic / d theta_j]) of ``residuals`` at ``th`` by
    forward-mode automatic differentiation: one tangent per parameter group, all in one vectorised ``jvp``."""
    m, p = th.shape
    dt, dev = th.dtype, th.device
    tangents = torch.zeros((len(groups), m, p), dtype=dt, device=dev)
    for g, params in enumerate(groups):
        tangents[g, :, params] = 1.0
    (r, q), (dr, dq) = torch.func.vmap(lambda t: torch.func.jvp(lambda x: residuals(x, rows), (th,), (t,)))(tangents)
    r, q = r[0], q[0]
    jr, jq = [None] * p, [None] * p
    for g, params in enumerate(groups):
        if len(params) == 1:
            jr[params[0]], jq[params[0]] = dr[g], dq[g]
            continue
        for i, j in enumerate(params):  # entries owned by another parameter of the group: zero
            jr[j] = dr[g] * (shared[1] == i).to(dt)
            jq[j] = dq[g] * (shared[2] == i).to(dt)
    return r, q, jr, jq
