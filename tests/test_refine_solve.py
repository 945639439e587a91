"""matcap.refine.solve: the batched Cholesky solve and the per-pixel Levenberg-Marquardt."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import matcap.refine.light_fit as L
import matcap.refine.photos as P
import matcap.refine.pixel_stage as PX
from matcap.evaluation.metrics import angular_error_map
from matcap.evaluation.toy import cone_lights
from matcap.refine import RefineSettings
from matcap.refine import synthetic as S
from matcap.refine.model import LightParams, PixelParams, shade_directional
from matcap.refine.solve import cholesky_solve, joint_levenberg_marquardt, levenberg_marquardt, robust_loss


def _spd(n: int, p: int, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    a = torch.randn(n, p, p, generator=g, dtype=torch.float64)
    return a @ a.transpose(1, 2) + 0.1 * torch.eye(p, dtype=torch.float64)


def test_cholesky_solve_matches_torch_linalg():
    h = _spd(50, 7)
    g = torch.randn(50, 7, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    x = cholesky_solve(h, g)
    assert torch.allclose(x, torch.linalg.solve(h, g), atol=1e-9, rtol=1e-9)


def test_cholesky_solve_does_not_depend_on_the_batch():
    h = _spd(40, 5).float()
    g = torch.randn(40, 5, generator=torch.Generator().manual_seed(2))
    whole = cholesky_solve(h, g)
    parts = torch.cat([cholesky_solve(h[:13], g[:13]), cholesky_solve(h[13:], g[13:])])
    assert torch.equal(whole, parts)


def test_cholesky_solve_several_right_hand_sides():
    h = _spd(30, 6)
    g = torch.randn(30, 6, 4, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    x = cholesky_solve(h, g)
    assert x.shape == (30, 6, 4)
    assert torch.allclose(x, torch.linalg.solve(h, g), atol=1e-9, rtol=1e-9)
    assert torch.equal(x[..., 2], cholesky_solve(h, g[..., 2]))


def test_cholesky_solve_bad_shapes():
    with pytest.raises(ValueError, match=r"\(N, P, P\).*\(3, 4, 4\) and \(3, 5\)"):
        cholesky_solve(torch.eye(4).expand(3, 4, 4), torch.zeros(3, 5))


def _exp_problem(seed: int = 0, outliers: bool = False):
    """200 problems y_i = a exp(-b t_i) at 12 samples t_i, each with its own (a, b)."""
    g = torch.Generator().manual_seed(seed)
    n = 200
    a = 0.5 + torch.rand(n, generator=g, dtype=torch.float64)
    b = 0.2 + torch.rand(n, generator=g, dtype=torch.float64)
    t = torch.linspace(0.0, 4.0, 12, dtype=torch.float64)
    y = a[:, None] * torch.exp(-b[:, None] * t[None])
    if outliers:
        y[:, 3] += 2.0  # one gross outlier per problem
    return a, b, t, y


def test_levenberg_marquardt_recovers_independent_problems():
    a, b, t, y = _exp_problem()

    def residuals(theta, rows):
        pred = theta[:, :1] * torch.exp(-theta[:, 1:2] * t[None])
        return pred - y[rows], torch.zeros_like(theta[:, :0])

    start = torch.stack([torch.ones_like(a), torch.full_like(b, 0.7)], 1)
    every = torch.arange(len(a))
    loss0 = robust_loss(*residuals(start, every), torch.ones_like(a), 0.1)
    out = levenberg_marquardt(residuals, start, torch.ones_like(a), 0.1, iters=25, tol=0.0)
    assert torch.allclose(out[:, 0], a, atol=1e-6) and torch.allclose(out[:, 1], b, atol=1e-6)
    assert robust_loss(*residuals(out, every), torch.ones_like(a), 0.1).max() < 1e-10 < float(loss0.min())


def test_levenberg_marquardt_ignores_an_outlier_and_honours_a_prior():
    a, b, t, y = _exp_problem(outliers=True)
    w = torch.ones_like(a)

    def residuals(theta, rows):
        pred = theta[:, :1] * torch.exp(-theta[:, 1:2] * t[None])
        return pred - y[rows], torch.zeros_like(theta[:, :0])

    start = torch.stack([torch.ones_like(a), torch.full_like(b, 0.7)], 1)
    out = levenberg_marquardt(residuals, start, w, 0.05, iters=40)
    assert (out[:, 0] - a).abs().max() < 0.01 and (out[:, 1] - b).abs().max() < 0.01  # least squares: ~0.2 off
    lsq = levenberg_marquardt(residuals, start, w, 1e3, iters=40)  # a huge scale: plain least squares
    assert (lsq[:, 0] - a).abs().mean() > 0.05

    # a strong quadratic prior on a pulls it to 1 whatever the photos say
    def with_prior(theta, rows):
        r, _ = residuals(theta, rows)
        return r, 100.0 * (theta[:, :1] - 1.0)

    held = levenberg_marquardt(with_prior, start, w, 0.05, iters=40)
    assert (held[:, 0] - 1.0).abs().max() < 0.01


def test_levenberg_marquardt_shared_tangent_gives_the_same_answer():
    """Three 'channels' each with its own gain (parameters 1-3 move disjoint entries) and a common decay."""
    g = torch.Generator().manual_seed(3)
    n, t = 100, torch.linspace(0.0, 3.0, 8, dtype=torch.float64)
    gain = 0.5 + torch.rand(n, 3, generator=g, dtype=torch.float64)
    decay = 0.3 + torch.rand(n, 1, generator=g, dtype=torch.float64)
    y = (gain[:, None, :] * torch.exp(-decay[:, :, None] * t[None, :, None])).reshape(n, -1)  # (n, 8 * 3)

    def residuals(theta, rows):
        pred = theta[:, None, 1:4] * torch.exp(-theta[:, 0:1, None] * t[None, :, None])
        return pred.reshape(len(rows), -1) - y[rows], 0.1 * (theta[:, 1:4] - 1.0)

    start = torch.cat([torch.full((n, 1), 0.8, dtype=torch.float64), torch.ones(n, 3, dtype=torch.float64)], 1)
    w = torch.ones(n, dtype=torch.float64)
    plain = levenberg_marquardt(residuals, start, w, 0.1, iters=15)
    owner = torch.arange(3).repeat(8)
    shared = levenberg_marquardt(residuals, start, w, 0.1, iters=15, shared=([1, 2, 3], owner, torch.arange(3)))
    assert torch.allclose(plain, shared, atol=1e-9)
    assert (plain[:, 0:1] - decay).abs().max() < 0.05


def test_levenberg_marquardt_never_raises_the_loss_and_reports_it():
    a, b, t, y = _exp_problem(seed=4)
    seen = []

    def residuals(theta, rows):
        pred = theta[:, :1] * torch.exp(-theta[:, 1:2] * t[None])
        return pred - y[rows], 0.01 * theta

    start = torch.stack([torch.full_like(a, 3.0), torch.full_like(b, 2.5)], 1)
    levenberg_marquardt(residuals, start, torch.ones_like(a), 0.1, iters=12, on_step=seen.append)
    assert len(seen) == 12 and all(math.isfinite(x) for x in seen)
    assert all(later <= earlier + 1e-12 for earlier, later in zip(seen, seen[1:]))
    assert seen[-1] < 0.05 * seen[0]


def test_levenberg_marquardt_bad_theta():
    with pytest.raises(ValueError, match=r"theta must be \(N, P\), got \(5,\)"):
        levenberg_marquardt(lambda th, rows: (th, th), torch.zeros(5), torch.ones(5), 0.1, iters=1)


def test_levenberg_marquardt_drops_finished_problems():
    """Problems that have converged stop being evaluated; the others carry on to the same answer."""
    a, b, t, y = _exp_problem(seed=5)
    y = y + 1e-3 * torch.sin(torch.arange(y.numel(), dtype=y.dtype)).reshape(y.shape)  # no loss reaches 0
    start = torch.stack([torch.ones_like(a), torch.full_like(b, 0.7)], 1)
    start[:100] = torch.stack([a[:100], b[:100]], 1) + 1e-3  # half of them start next to their answer

    def run(tol):
        sizes = []

        def residuals(theta, rows):
            sizes.append(len(rows))
            pred = theta[:, :1] * torch.exp(-theta[:, 1:2] * t[None])
            return pred - y[rows], torch.zeros_like(theta[:, :0])

        return levenberg_marquardt(residuals, start, torch.ones_like(a), 0.1, iters=30, tol=tol), sizes

    out, sizes = run(1e-4)
    assert (out - torch.stack([a, b], 1)).abs().max() < 5e-3  # the noise moves the answer a little
    assert sizes[0] == 200 and sizes[-1] < 100
    every_out, every = run(-1.0)  # never done
    assert min(every) == 200 and sum(every) > 1.5 * sum(sizes)
    assert (every_out - out).abs().max() < 1e-4


def _glossy_sphere_problem(side: int = 48):
    """The fit's per-pixel problem for a glossy sphere rendered by its own model under 12 known lights, from
    perturbed maps: (truth, start, problem, lights, start parameters)."""
    truth = S.sphere_maps(side)
    m = truth.mask
    k = 12
    dirs = torch.from_numpy(cone_lights(k, 50.0, seed=1)).float()
    irr = torch.full((k, 3), 2.5)
    with torch.no_grad():
        px = shade_directional(torch.from_numpy(truth.normal[m]), torch.from_numpy(truth.base_color[m]),
                               torch.full((int(m.sum()),), 0.25), torch.zeros(int(m.sum())), dirs, irr,
                               torch.zeros(1, 9, 3)).numpy()
    scale = 0.5 / float(px.mean())
    obs = np.zeros((k,) + m.shape + (3,), np.float32)
    obs[:, m] = px * scale
    start = S.perturb(truth)
    prob = P._Problem(torch, obs, m, P._maps_arrays(start), np.ones(m.shape, np.float32),
                      np.full((k, 3), np.inf, np.float32), torch.device("cpu"))
    lights = LightParams("directional", dirs.clone(), torch.log(irr * scale), torch.zeros(1, 9, 3))
    return truth, start, prob, lights, PixelParams.from_maps(prob.ns, prob.b0, prob.r0, prob.m0)


def test_the_pixel_solve_converges():
    """The fit's per-pixel stage alone (true lights given), on a glossy sphere rendered by the fit's own model from
    perturbed maps: 20 Levenberg-Marquardt iterations reach a loss below 0.14 (measured 0.074; first-order Adam
    reached 0.281 in 150 steps and 0.253 in 1000) and normals within 1 degree (measured 0.87)."""
    truth, start, prob, lights, px0 = _glossy_sphere_problem()
    m = truth.mask

    def solve(settings, iters):
        out = PX._solve_pixels(torch, prob, px0, lights, settings, settings.loss.cauchy, iters,
                               P._Bar(None, settings), "maps")
        normal = np.zeros(m.shape + (3,), np.float32)
        normal[m] = out.normal().detach().numpy()
        with torch.no_grad():
            per, _ = P._loss(torch, prob, out, lights, settings, settings.loss.cauchy)
        return float(angular_error_map(normal, truth.normal, m)[m].mean()), float(per.mean())

    s = RefineSettings(seed=0)
    err_lm10, loss_lm10 = solve(s, 10)
    err_lm, loss_lm = solve(s, 20)
    assert angular_error_map(start.normal, truth.normal, m)[m].mean() > 5.0
    assert loss_lm <= loss_lm10 and loss_lm < 0.14, (loss_lm, loss_lm10)
    assert err_lm < 1.0, err_lm


def test_the_pixel_solve_does_not_depend_on_the_chunks():
    _, _, prob, lights, px0 = _glossy_sphere_problem(32)
    outs = []
    for obs in (262144, 12 * 300, 12 * 97):  # one chunk; 300 pixels; 256 (the smallest chunk)
        s = RefineSettings(seed=0).replace({"pixels.lm_observations": obs})
        outs.append(PX._solve_pixels(torch, prob, px0, lights, s, s.loss.cauchy, 8, P._Bar(None, s), "maps"))
    assert len(prob) > 600
    for other in outs[1:]:
        assert all(torch.equal(a, b) for a, b in zip(outs[0].tensors(), other.tensors()))


@pytest.mark.parametrize("mixed", [False, True])
@pytest.mark.parametrize("fit_brdf", [True, False])
def test_the_pixel_system_is_the_normal_equations_of_the_jacobian(mixed, fit_brdf):
    """The per-pixel solve's Gauss-Newton system, built in the model's layout (a base colour channel's zeros
    skipped, clipped and shadowed observations through their weight), is the generic one of its residuals'
    Jacobian (solve._normal_equations with the Cauchy loss's IRLS weights): with clipped observations, cast-shadow
    bounds, per-pixel weights, the outline's coverage (``mixed``) and with roughness and metallic held."""
    from matcap.refine.solve import _normal_equations

    _, _, prob, lights, px0 = _glossy_sphere_problem(32)
    sat = np.full((prob.obs.shape[0], 3), float(prob.obs.max()) * 0.8, np.float32)  # the highlights clip
    truth = S.sphere_maps(32)
    weight = np.random.default_rng(0).uniform(0.5, 1.5, truth.mask.shape).astype(np.float32)
    obs = np.zeros((prob.obs.shape[0],) + truth.mask.shape + (3,), np.float32)
    obs[:, truth.mask] = prob.obs.numpy()
    obs[:3, :, :16] *= 0.2  # three photos' left half in cast shadow
    prob = P._Problem(torch, obs, truth.mask, P._maps_arrays(S.perturb(truth)), weight, sat, torch.device("cpu"),
                      shadow=0.3)
    s = RefineSettings(seed=0).replace({"model.fit_brdf": fit_brdf})
    start = list(px0.tensors())
    if mixed:
        prob.backdrop = torch.rand(prob.obs.shape[0], len(prob), 3, generator=torch.Generator().manual_seed(3))
        start.append(torch.full((len(prob),), 1.5))
    theta, _, jacobian, system, _ = PX._pixel_residuals(torch, prob, start, s)
    theta = theta + 0.05 * torch.randn(theta.shape, generator=torch.Generator().manual_seed(4))
    rows = torch.arange(len(theta))
    live = lights.detached()
    w = prob.weight / 3.0
    with torch.no_grad():
        r, q, jr, jq = jacobian(theta, rows, live)
        grad0, hess0 = _normal_equations(r, q, jr, jq, w[:, None] * 2.0 / (0.15 ** 2 + r * r))
        grad, hess = system(theta, rows, live, w, 0.15)
    assert float((r == 0).float().mean()) > 0.05  # clipped and shadowed observations are in
    assert grad.shape == grad0.shape and hess.shape == hess0.shape == (len(theta),) + 2 * (theta.shape[1],)
    assert float((grad - grad0).abs().max()) <= 1e-5 * float(grad0.abs().max())
    assert float((hess - hess0).abs().max()) <= 1e-5 * float(hess0.abs().max())


def test_the_light_fit_does_not_depend_on_the_thread_count(monkeypatch):
    """The light fit sums each step's loss and gradient over two halves of its pixels, side by side where torch
    has two threads: the lights and the last data term are the same bits on one thread and on two. (The process
    is told it may use two CPUs, so that the halves run side by side on a one-CPU machine too.)"""
    monkeypatch.setattr(P.os, "sched_getaffinity", lambda pid: {0, 1}, raising=False)
    assert P._workers(2) == 2
    _, _, prob, lights, _ = _glossy_sphere_problem(32)
    start = LightParams("directional", lights.vec.clone(), lights.log_intensity + 0.3, lights.sh.clone())
    s = RefineSettings(seed=0)
    was = torch.get_num_threads()
    outs = []
    try:
        for threads in (1, 2):
            torch.set_num_threads(threads)
            trial = LightParams("directional", *(t.clone() for t in start.tensors()))
            outs.append(L._fit_lights(torch, prob, trial, s, P._Bar(None, s), "lights", 30))
    finally:
        torch.set_num_threads(was)
    (one, data_one), (two, data_two) = outs
    assert all(torch.equal(a, b) for a, b in zip(one.tensors(), two.tensors()))
    assert data_one == data_two
    assert float((one.log_intensity - start.log_intensity).abs().max()) > 1e-3  # the fit moved the lights


def test_levenberg_marquardt_stops_where_the_model_promises_nothing():
    """At its minimum (in float32, where a step's gain is lost in rounding and the step may be rejected) a problem
    is done within a few iterations: the Gauss-Newton model predicts no gain, so a rejected step there is not
    taken for a step that was only too long (without that rule the damping has to grow to ``LAM_DONE`` first: 24
    iterations here)."""
    a, b, t, y = _exp_problem(seed=3)
    y = y + 1e-3 * torch.sin(torch.arange(y.numel(), dtype=y.dtype)).reshape(y.shape)
    t32, y32 = t.float(), y.float()

    def residuals(theta, rows):
        sizes.append(len(rows))
        pred = theta[:, :1] * torch.exp(-theta[:, 1:2] * t32[None])
        return pred - y32[rows], torch.zeros_like(theta[:, :0])

    sizes: list[int] = []
    start = torch.stack([a, b], 1).float()
    best = levenberg_marquardt(residuals, start, torch.ones(len(a)), 0.1, iters=60, tol=-1.0)  # never done
    sizes = []
    again = levenberg_marquardt(residuals, best, torch.ones(len(a)), 0.1, iters=30, tol=1e-4)
    assert len(sizes) <= 5, sizes  # the loss at the start, then four iterations at most
    assert (again - best).abs().max() < 1e-5


def _gains_problem(seed: int = 0):
    """300 problems y_ik = exp(a_i x_k) + s_k at 8 samples: a_i each problem's own, the offsets s_k shared."""
    g = torch.Generator().manual_seed(seed)
    n, k = 300, 8
    a = torch.rand(n, generator=g, dtype=torch.float64) * 0.8 - 0.4
    s = torch.randn(k, generator=g, dtype=torch.float64) * 0.5
    x = torch.rand(k, generator=g, dtype=torch.float64) + 0.5
    y = torch.exp(a[:, None] * x[None]) + s[None]

    def residuals(th, sh):
        return torch.exp(th[:, :1] * x[None]) + sh[None] - y, th.new_zeros(len(th), 0)

    def jacobian(th, sh):
        r, q = residuals(th, sh)
        return r, q, [x[None] * torch.exp(th[:, :1] * x[None])], [q], [(torch.arange(k), torch.ones_like(r))], []

    return a, s, residuals, jacobian


def test_joint_levenberg_marquardt_recovers_own_and_shared_parameters():
    a, s, residuals, jacobian = _gains_problem()
    n, k = len(a), len(s)
    seen = []
    th, sh, done = joint_levenberg_marquardt(residuals, jacobian, torch.zeros(n, 1, dtype=torch.float64),
                                             torch.zeros(k, dtype=torch.float64), torch.ones(n, dtype=torch.float64),
                                             10.0, iters=50, tol=0.0, on_step=seen.append)
    assert (th[:, 0] - a).abs().max() < 1e-6 and (sh - s).abs().max() < 1e-6
    assert done == len(seen) and all(later <= earlier for earlier, later in zip(seen, seen[1:]))


def test_joint_levenberg_marquardt_matches_a_general_minimiser():
    """A prior on the own parameters and on the shared ones through a quadratic slot (a level every problem's
    prior refers to): the solver lands where L-BFGS on the same loss does (to 0.1 % of the loss: with outliers the
    Gauss-Newton model of the Cauchy loss converges linearly at the end)."""
    g = torch.Generator().manual_seed(1)
    n, k = 120, 6
    a = torch.rand(n, generator=g, dtype=torch.float64) + 0.5
    x = torch.rand(k, generator=g, dtype=torch.float64) + 0.5
    z = torch.rand(k, generator=g, dtype=torch.float64)
    y = 1.7 * x[None] + a[:, None] * z[None] + 0.05 * torch.randn(n, k, generator=g, dtype=torch.float64)
    y[::7, 2] += 3.0  # outliers the Cauchy loss discounts
    a0 = 0.6 * a * (1.0 + 0.2 * torch.randn(n, generator=g, dtype=torch.float64))  # the prior: a's pattern, 0.6 x

    def residuals(th, sh):  # shared: (log gain, log level of the prior)
        return torch.exp(sh[0]) * x[None] + th[:, :1] * z[None] - y, 0.3 * (th[:, :1] - torch.exp(sh[1]) * a0[:, None])

    def jacobian(th, sh):
        r, q = residuals(th, sh)
        jr = [z[None].expand(n, -1)]
        jq = [torch.full_like(q, 0.3)]
        slots = [(torch.zeros(k, dtype=torch.int64), torch.exp(sh[0]) * x[None].expand(n, -1))]
        qslots = [(torch.ones(1, dtype=torch.int64), -0.3 * torch.exp(sh[1]) * a0[:, None])]
        return r, q, jr, jq, slots, qslots

    w = torch.ones(n, dtype=torch.float64)
    th, sh, _ = joint_levenberg_marquardt(residuals, jacobian, a0[:, None].clone(),
                                          torch.zeros(2, dtype=torch.float64), w, 0.2, iters=100, tol=0.0)
    tt = a0[:, None].clone().requires_grad_(True)
    ss = torch.zeros(2, dtype=torch.float64, requires_grad=True)
    opt = torch.optim.LBFGS([tt, ss], max_iter=2000, tolerance_grad=1e-12, tolerance_change=1e-15,
                            line_search_fn="strong_wolfe")

    def closure():
        opt.zero_grad()
        loss = robust_loss(*residuals(tt, ss), w, 0.2).sum()
        loss.backward()
        return loss

    opt.step(closure)
    ours = float(robust_loss(*residuals(th, sh), w, 0.2).sum())
    best = float(robust_loss(*residuals(tt.detach(), ss.detach()), w, 0.2).sum())
    assert ours <= best * 1.001
    assert (sh - ss.detach()).abs().max() < 0.01 and (th - tt.detach()).abs().max() < 0.02
    assert abs(float(sh[0].exp()) - 1.7) < 0.05 and abs(float(sh[1].exp()) - 1 / 0.6) < 0.1


def test_joint_levenberg_marquardt_keeps_a_projection():
    """project: every trial is mapped onto the constraint (here: the own parameters' mean held at 0)."""
    a, s, residuals, jacobian = _gains_problem(seed=2)
    n, k = len(a), len(s)
    th, sh, _ = joint_levenberg_marquardt(residuals, jacobian, torch.full((n, 1), 0.3, dtype=torch.float64),
                                          torch.zeros(k, dtype=torch.float64), torch.ones(n, dtype=torch.float64),
                                          10.0, iters=30, project=lambda t: t - t.mean(0))
    assert abs(float(th.mean())) < 1e-12
    free, _, _ = joint_levenberg_marquardt(residuals, jacobian, torch.zeros(n, 1, dtype=torch.float64),
                                           torch.zeros(k, dtype=torch.float64), torch.ones(n, dtype=torch.float64),
                                           10.0, iters=30)
    assert abs(float(free.mean()) - float(a.mean())) < 1e-6 and abs(float(a.mean())) > 1e-3


def test_joint_levenberg_marquardt_bad_shapes():
    with pytest.raises(ValueError, match=r"theta must be \(N, P\) and shared \(S,\), got \(5,\) and \(2,\)"):
        joint_levenberg_marquardt(None, None, torch.zeros(5), torch.zeros(2), torch.ones(5), 0.1, iters=1)
