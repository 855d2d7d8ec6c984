"""The road's relief from sparse points in road coordinates (pavemap.mesh.relief), the anchoring of a trained
surface to the ground points and their held-out split (issue 12: geometry without LiDAR)."""

from __future__ import annotations

import numpy as np

from pavemap.geometry.grid import GridSpec
from pavemap.mesh.geometry import anchor_correction
from pavemap.mesh.relief import ReliefFit, fit_relief


def _cross_section(t: np.ndarray, s: np.ndarray) -> np.ndarray:
    """A road 10 m wide with a 2 % crown, a 0.12 m kerb at t = -5 and a sidewalk rising 2 % beyond it, on a
    slowly varying unevenness along s (m)."""
    road = -0.02 * np.abs(t) + 0.01 * np.sin(s / 15.0)
    side = 0.12 + 0.02 * (-t - 5.0) + 0.01 * np.sin(s / 15.0) - 0.1
    return np.where(t < -5.0, side, road)


def _points(rng: np.random.Generator, n: int, gap: tuple[float, float] | None = None) -> tuple[np.ndarray, ...]:
    s = rng.uniform(0, 100, n)
    t = rng.uniform(-8, 7, n)
    if gap is not None:  # a stretch of plain asphalt no point falls on
        keep = ~((t > gap[0]) & (t < gap[1]) & (s > 40) & (s < 52))
        s, t = s[keep], t[keep]
    return s, t, _cross_section(t, s) + rng.normal(0, 0.004, len(s))


def test_fit_recovers_a_cross_section_with_a_kerb_and_fills_a_gap_along_the_road():
    rng = np.random.default_rng(0)
    s, t, r = _points(rng, 3000, gap=(-3.0, 3.0))
    qs, qt = np.meshgrid(np.arange(2, 98, 0.5), np.arange(-7.5, 6.5, 0.1))
    qs, qt = qs.ravel(), qt.ravel()
    est = fit_relief(s, t, r, qs, qt)
    assert est is not None and est.shape == qs.shape and np.isfinite(est).all()
    err = est - _cross_section(qt, qs)
    away = np.abs(qt + 5.0) > 0.25  # the kerb itself is a step of one lattice cell
    assert np.sqrt(np.mean(err[away] ** 2)) < 0.008
    gap = (qt > -2.5) & (qt < 2.5) & (qs > 41) & (qs < 51)
    # 12 m of plain asphalt without a point keeps its crown: taken from the same offset before and after
    assert np.abs(err[gap]).max() < 0.015 and np.median(np.abs(err[gap])) < 0.006
    # the kerb stays a step: within 0.3 m across it the fitted height rises by most of its 0.12 m
    lo = est[np.abs(qt + 4.7) < 0.05].mean()
    hi = est[np.abs(qt + 5.3) < 0.05].mean()
    assert hi - lo > 0.08


def test_fit_is_robust_to_mismatched_points_and_refuses_too_few():
    rng = np.random.default_rng(1)
    s, t, r = _points(rng, 2000)
    bad = rng.random(len(r)) < 0.1
    r_bad = np.where(bad, r + rng.choice([-0.3, 0.3], len(r)), r)
    qs, qt = rng.uniform(5, 95, 2000), rng.uniform(-4, 4, 2000)
    est = fit_relief(s, t, r_bad, qs, qt)
    assert est is not None and np.median(np.abs(est - _cross_section(qt, qs))) < 0.005
    assert fit_relief(s[:50], t[:50], r[:50], qs, qt) is None
    # a lattice beyond the node budget is refused, not allocated
    assert fit_relief(s, t, r, qs, qt, ReliefFit(max_nodes=1000)) is None


def test_banded_solve_equals_the_sparse_solve_on_both_lattice_orders():
    import scipy.sparse as sp
    from scipy.sparse.linalg import spsolve

    from pavemap.mesh.relief import _bilinear, _difference, _gram, _solve_spd

    rng = np.random.default_rng(4)
    fit = ReliefFit()
    for ns, nt in ((12, 40), (40, 12)):  # numbered along s first, then along t first
        n = ns * nt
        A = _bilinear(rng.uniform(0, (ns - 1) * fit.ds, 200), rng.uniform(0, (nt - 1) * fit.dt, 200), 0.0, 0.0,
                      fit, ns, nt)
        M = (A.T @ A + _gram(_difference(ns, nt, 0, 2)) + 0.01 * _gram(_difference(ns, nt, 1, 1))
             + 1e-3 * sp.identity(n)).tocsr()
        b = rng.normal(size=n)
        ref = spsolve(M.tocsc(), b)
        # float32 factor refined in float64: to 1e-8 of the solution's scale (1e-8 m on the bench drives) ...
        assert np.allclose(_solve_spd(M, b, ns, nt), ref, rtol=0, atol=1e-8 * np.abs(ref).max())
        # ... and the float64 factor where the refinement does not converge (here: no refinement allowed)
        assert np.allclose(_solve_spd(M, b, ns, nt, max_refine=0), ref, rtol=0, atol=1e-9)
    indefinite = sp.diags(np.r_[1.0, -1.0, np.ones(6)]).tocsr()  # not SPD: the general solve
    assert np.allclose(_solve_spd(indefinite, np.ones(8), 2, 4), np.r_[1.0, -1.0, np.ones(6)])


def test_anchoring_removes_a_drift_of_the_trained_surface():
    """Training lifted the surface by 3 cm: the correction fitted to the points' residuals takes it back."""
    rng = np.random.default_rng(2)
    spec = GridSpec(-5.0, -8.0, 0.1, 1101, 161)
    X, Y = np.meshgrid(spec.x0 + np.arange(spec.nx) * spec.res, spec.y0 + np.arange(spec.ny) * spec.res)
    truth = _cross_section(Y, X)
    xy = np.stack([rng.uniform(0, 100, 3000), rng.uniform(-7.5, 7.5, 3000)], 1)
    pts = np.column_stack([xy, _cross_section(xy[:, 1], xy[:, 0]) + rng.normal(0, 0.004, len(xy))])
    traj = np.stack([np.arange(0.0, 101.0, 1.0), np.zeros(101)], 1)
    vxy = np.stack([X.ravel(), Y.ravel()], 1)
    drifted = truth + 0.03 + 0.01 * np.sin(X / 30.0)
    corr = anchor_correction(pts, spec, drifted, vxy, traj)
    assert corr is not None and corr.shape == (len(vxy),) and abs(np.median(corr) + 0.03) < 0.01  # the 3 cm lift
    fixed = drifted.ravel() + corr
    inner = (vxy[:, 0] > 2) & (vxy[:, 0] < 98)
    assert abs(np.mean((fixed - truth.ravel())[inner])) < 0.002
    assert np.sqrt(np.mean(((fixed - truth.ravel())[inner]) ** 2)) < 0.01
    assert anchor_correction(None, spec, drifted, vxy, traj) is None


def test_held_out_ground_points_are_disjoint_and_keep_their_observations():
    from pavemap.mesh.ground_points import GroundPoints

    n = 40
    pts = np.column_stack([np.arange(n, dtype=float), np.zeros(n), np.zeros(n)])
    obs_point = np.repeat(np.arange(n), 2)
    gp = GroundPoints([(0, "c"), (1, "c")], pts, np.full(n, 2), np.zeros(n), np.ones(n), np.ones(n, bool),
                      obs_point, np.tile([0, 1], n), np.stack([obs_point * 1.0, obs_point * 2.0], 1),
                      obs_point * 0.5, False, True, "")
    fit, check = gp.split(8)
    assert len(fit) + len(check) == n and len(check) == 5
    assert not set(fit.points[:, 0]) & set(check.points[:, 0])
    for part in (fit, check):  # each observation still points at its own point
        assert np.array_equal(part.points[part.obs_point, 0], part.obs_uv[:, 0])
        assert np.array_equal(part.obs_depth, part.obs_uv[:, 0] * 0.5)


def _kerb_drive(gap: tuple[float, float]) -> tuple[np.ndarray, ...]:
    """Points on the road and the sidewalk of :func:`_cross_section` but none within ``gap`` of t (the kerb at
    t = -5 and the ground beside it, as forward cameras leave it), and a query lattice over all of it."""
    rng = np.random.default_rng(3)
    s, t = rng.uniform(0, 100, 3000), rng.uniform(-9, 7, 3000)
    keep = (t > gap[1]) | (t < gap[0])
    s, t = s[keep], t[keep]
    qs, qt = np.meshgrid(np.arange(2, 98, 0.25), np.arange(-8.5, 6.5, 0.1))
    return s, t, _cross_section(t, s) + rng.normal(0, 0.004, len(s)), qs.ravel(), qt.ravel()


def test_the_fit_steps_where_the_sides_change_instead_of_rounding_the_kerb_off():
    s, t, r, qs, qt = _kerb_drive((-6.0, -4.0))
    side = np.where(qt >= -5.0, 1, 0)
    side[(qs > 60) & (qs < 62)] = -1  # vertices no labelled pixel reached: no break there
    truth, near = _cross_section(qt, qs), np.abs(qt + 5.0) < 1.0
    rounded = fit_relief(s, t, r, qs, qt) - truth
    stepped = fit_relief(s, t, r, qs, qt, side_q=side) - truth
    rms = lambda e, m: float(np.sqrt(np.mean(e[m] ** 2)))  # noqa: E731
    assert rms(rounded, near) > 0.03  # the smooth fit spreads the 0.12 m step over the gap
    assert rms(stepped, near) < 0.02
    assert rms(stepped, ~near) <= rms(rounded, ~near) + 0.001  # and nothing gets worse away from the kerb
    # one side only: nothing to break
    assert np.allclose(fit_relief(s, t, r, qs, qt, side_q=np.ones_like(side)), rounded + truth, atol=1e-6)


def test_a_refit_from_the_first_fits_weights_matches_a_fit_from_scratch_in_fewer_rounds(monkeypatch):
    import pavemap.mesh.relief as relief

    s, t, r, qs, qt = _kerb_drive((-5.6, -4.4))
    side = np.where(qt >= -5.0, 1, 0)
    solves = []
    solve = relief._solve_spd
    monkeypatch.setattr(relief, "_solve_spd", lambda *a, **k: solves.append(1) or solve(*a, **k))
    state: dict = {}
    fit_relief(s, t, r, qs, qt, state=state)
    assert len(solves) == ReliefFit().iterations and state["w"].shape == r.shape
    solves.clear()
    warm = fit_relief(s, t, r, qs, qt, side_q=side, state=state)
    assert len(solves) == ReliefFit().refit_iterations
    cold = fit_relief(s, t, r, qs, qt, side_q=side)
    assert np.sqrt(np.mean((warm - cold) ** 2)) < 0.002


def test_a_few_points_far_off_the_road_leave_no_bump():
    rng = np.random.default_rng(4)
    s, t = rng.uniform(0, 100, 1500), rng.uniform(-4, 4, 1500)
    r = _cross_section(t, s) + rng.normal(0, 0.004, len(s))
    so, to = 50 + rng.normal(0, 0.3, 6), 1 + rng.normal(0, 0.2, 6)  # a car's bonnet matched as ground
    S, T, R = np.r_[s, so], np.r_[t, to], np.r_[r, _cross_section(to, so) + 0.35]
    qs, qt = np.meshgrid(np.arange(45, 55, 0.1), np.arange(-1, 3, 0.1))
    qs, qt = qs.ravel(), qt.ravel()
    huber = fit_relief(S, T, R, qs, qt, ReliefFit(reject_m=np.inf)) - _cross_section(qt, qs)
    rejected = fit_relief(S, T, R, qs, qt) - _cross_section(qt, qs)
    assert np.abs(huber).max() > 0.02  # Huber's linear tail still lets six points lift the road
    assert np.abs(rejected).max() < 0.008
