"""The photometric refinement and the multi-view consistency self-check (issue 47) on a scene whose road
texture the views resolve (tests/mesh_scene.py at 240 x 150 px, a forward and a rearward camera)."""

from __future__ import annotations

import pytest
import torch

from mesh_scene import ROAD_HALF, read_scene
from pavemap.io.truth import read_truth_height
from pavemap.mesh import MeshConfig, reconstruct
from pavemap.mesh.model import RoadMeshModel
from pavemap.mesh.refine import consistency_loss, find_pairs, pool_images, residuals, view_stack
from pavemap.mesh.refine_run import consistency_metrics, refine_offset
from pavemap.mesh.setup import prepare


def _cfg(**kw) -> MeshConfig:
    base = dict(resolution=0.1, crop_m=3.0, render_scale=1.0, eval_scale=0.5, holdout_every=0, device="cpu",
                threads=1, resume=False, view_range_m=0.0, ground_points="off", init_height_search=False)
    base.update(kw)
    return MeshConfig(**base)


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """The scene, its training pool and grid, and the true heights (Nv,) of the grid's vertices."""
    seq = read_scene(tmp_path_factory.mktemp("refine") / "seq", frames=10, width=240, height=150, step=0.6,
                     cams=(0.0, 180.0))
    cfg = _cfg()
    data = prepare(seq, cfg, torch.device("cpu"), lambda msg: None)
    z, inside = read_truth_height(seq.root).height_at(torch.from_numpy(data.grid.vertex_xy()))
    assert inside.all()
    return seq, cfg, data, z.float()


def _model(data, z: torch.Tensor) -> RoadMeshModel:  # noqa: ANN001
    return RoadMeshModel(data.grid, len(data.classes), 2, 8, z.numpy())


def _bias(model: RoadMeshModel, truth: torch.Tensor) -> float:
    return float((model.current_heights() - truth).mean())


@pytest.mark.parametrize("offset", [0.10, -0.10])
def test_refinement_pulls_a_shifted_surface_back(world, offset):
    _, cfg, data, truth = world
    model = _model(data, truth + offset)
    done = refine_offset(model, data.pool, data.pool.T, cfg)
    after = _bias(model, truth)
    assert abs(after) <= 0.5 * abs(offset), (offset, after, done)
    assert abs(after) < 0.03
    assert done["offset_m"] * offset < 0  # it moved towards the truth


def test_consistency_flags_a_shifted_surface_and_not_the_true_one(world):
    _, cfg, data, truth = world
    right = consistency_metrics(_model(data, truth), data.pool, data.pool.T, cfg)
    wrong = consistency_metrics(_model(data, truth + 0.08), data.pool, data.pool.T, cfg)
    assert not right["flagged"] and abs(right["offset_m"]) < cfg.check_max_consistency_m, right
    assert wrong["flagged"] and -0.11 < wrong["offset_m"] < -0.05, wrong


def test_analytic_height_derivative_matches_autograd(world):
    """The Gauss-Newton solve's dr/dz (refine.residuals) against autograd of the reference loss."""
    _, cfg, data, truth = world
    rgb, mask = pool_images(data.pool)
    T = data.pool.T.double().clone()
    xy64 = torch.from_numpy(data.grid.vertex_xy())
    origin = torch.cat([xy64.mean(0), truth.double().mean()[None]])
    T[:, :3, 3] -= origin
    st = view_stack(rgb, mask, data.pool.K, T.float(), 1.0)
    xy = (xy64 - origin[:2]).float()[::7]
    z = ((truth.double() - origin[2]).float() + 0.03)[::7].clone()
    pt, view = find_pairs(st, xy, z, cfg.max_dist, 8)
    assert pt.numel() > 1000
    res = residuals(st, pt, view, xy, z, z.shape[0])
    w = res.w.detach()
    zz = z.clone().requires_grad_(True)
    consistency_loss(st, pt, view, xy, zz, w).backward()
    analytic = torch.zeros_like(z).index_add_(0, pt, 2 * w * (res.r * res.J).sum(1))
    seen = analytic.abs() > 0
    assert seen.sum() > 100
    err = (zz.grad[seen] - analytic[seen]).abs().max() / analytic[seen].abs().max()
    assert err < 1e-3, float(err)


def test_a_run_with_refine_records_it(world):
    seq, _, _, _ = world
    cfg = _cfg(refine=True, consistency_check=True, camera_height=1.62)  # the prior 12 cm off the truth
    mesh, m = reconstruct(seq, None, cfg, progress=False)
    assert "refine" in m and "consistency" in m
    truth = read_truth_height(seq.root)
    s = mesh.surface
    xy = s.grid_xy()[s.valid].double()
    zt, inside = truth.height_at(xy)
    road = inside & (xy[:, 1].abs() < ROAD_HALF - 0.2)  # the flat initial surface has no kerb: the road's bias
    bias = float((s.heights[s.valid].double()[road] - zt[road]).mean())
    assert abs(bias) < 0.03, (bias, m["refine"])
    assert not m["consistency"]["flagged"], m["consistency"]


def test_heldout_psnr_counts_only_textured_faces(world):
    """Pixels on vertices no training view textured carry the bake's gap fill, not a reconstruction: the
    held-out PSNR leaves them out and says their share (the first frame of a real drive sees such road)."""
    from mesh_scene import texture
    from pavemap.mesh.evaluate import evaluate_pool

    _, cfg, data, truth = world
    model = _model(data, truth)
    with torch.no_grad():
        model.rgb.copy_(torch.from_numpy(texture(data.grid.vertex_xy())).float())
    heights = model.dense_heights(0.0)
    good = evaluate_pool(model, data.pool, heights, cfg.max_dist)
    seen = torch.from_numpy(data.grid.vertex_xy()[:, 0] < 0)  # the far half untextured...
    with torch.no_grad():
        model.rgb[~seen] = torch.tensor([1.0, 0.0, 1.0])  # ...and filled with a colour the road never has
    ev = evaluate_pool(model, data.pool, heights, cfg.max_dist, seen=seen)
    assert 0.2 < ev["textured_share"] < 0.8, ev
    assert ev["psnr_all"] < good["psnr"] - 5 < ev["psnr"] - 4, (good, ev)
    assert "psnr_all" not in good and "textured_share" not in good


def test_refinement_leaves_the_surface_when_the_consistency_has_no_minimum(world, monkeypatch):
    """A scan whose best offset is its range's edge (the real nuScenes clips: 31 and 63 cm walked down) found a
    slope, not a height: the surface stays, the result says so, and a run warns."""
    import pavemap.mesh.refine_run as rr

    _, cfg, data, truth = world
    calls = []

    def edge_then_less(*a, **kw):  # the first scan a small step, then the edge of the range
        calls.append(kw["offsets"])
        return (0.04 if len(calls) == 1 else -max(kw["offsets"])), []

    monkeypatch.setattr(rr, "consistency_scan", edge_then_less)
    model = _model(data, truth + 0.05)
    before = model.current_heights().clone()
    done = rr.refine_offset(model, data.pool, data.pool.T, cfg)
    assert done["no_minimum"] and done["offset_m"] == 0.0, done
    assert torch.allclose(model.current_heights(), before), "the surface moved"
    assert len(calls) == 2
    warned: list[str] = []
    rr.record(model, data.pool, data.pool.T, _cfg(), done, warned.append, {})
    assert warned and "no minimum" in warned[0]


def test_footprints_match_the_ground_intersections_and_far_views_are_left_out():
    """A pixel's road footprint (refine.footprints) against the ray-plane intersections of its corners, and
    find_pairs keeping only the views whose footprint is at most FOOTPRINT_RATIO x the sharpest one's."""
    from pavemap.mesh.refine import FOOTPRINT_RATIO, ViewStack, footprints

    K = torch.tensor([[100.0, 0, 50], [0, 100.0, 30], [0, 0, 1]])
    Rcw = torch.tensor([[0.0, -1, 0], [0, 0, -1], [1, 0, 0]])  # camera looking along +x, level, at 1.5 m
    views = []
    for cx in (0.0, -1.0, -12.0):  # two views near the points, one far behind them
        c = torch.tensor([cx, 0.0, 1.5])
        views.append(K @ torch.cat([Rcw, -(Rcw @ c)[:, None]], 1))
    P = torch.stack(views)
    pts = torch.tensor([[6.0, 0.3], [8.0, -0.5]])
    z = torch.tensor([0.02, -0.03])
    X = torch.cat([pts, z[:, None], torch.ones(2, 1)], 1)
    p = torch.einsum("vij,pj->pvi", P, X)
    fp = footprints(P, p[..., 2], z)
    Minv = torch.linalg.inv(P[:, :, :3])
    for i in range(2):
        for v in range(3):
            uv = p[i, v, :2] / p[i, v, 2]

            def ground(du: float, dv: float, i=i, v=v, uv=uv) -> torch.Tensor:
                d = Minv[v] @ torch.tensor([uv[0] + du, uv[1] + dv, 1.0])
                c = -Minv[v] @ P[v, :, 3]
                return (c + (z[i] - c[2]) / d[2] * d)[:2]

            gu = (ground(0.01, 0) - ground(-0.01, 0)) / 0.02
            gv = (ground(0, 0.01) - ground(0, -0.01)) / 0.02
            fd = float((gu[0] * gv[1] - gu[1] * gv[0]).abs().sqrt())
            assert abs(float(fp[i, v]) - fd) < 1e-3 * fd, (i, v, float(fp[i, v]), fd)
    assert (fp[:, 2] > FOOTPRINT_RATIO * fp[:, 0]).all()  # the far view's pixels cover over 3x the road
    H, W = 60, 100
    st = ViewStack(torch.zeros(3, 3 * H * W), torch.ones(3 * H * W, dtype=torch.bool), P,
                   torch.tensor([[0.0, 0, 1.5], [-1.0, 0, 1.5], [-12.0, 0, 1.5]]), H, W)
    pt, view = find_pairs(st, pts, z, 80.0, 8)
    assert sorted(view.tolist()) == [0, 0, 1, 1], view
    pt, view = find_pairs(st, pts, z, 80.0, 8, footprint_ratio=0.0)  # 0: every view within reach
    assert sorted(view.tolist()) == [0, 0, 1, 1, 2, 2], view
