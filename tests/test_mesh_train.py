"""Stage-1 training end to end on a tiny textured scene (tests/mesh_scene.py), outputs, bad input."""

from __future__ import annotations

import copy
import json
import warnings

import numpy as np
import pytest
import torch
import trimesh

from mesh_scene import look, make_scene, read_scene
from pavemap.errors import PavemapError
from pavemap.mesh import MeshConfig, load_mesh, reconstruct, render_view
from pavemap.mesh.data import split_frames
from pavemap.mesh.model import HeightMLP, build_grid, positional_encoding
from pavemap.synth import perturb_poses, pose_errors


def _cfg(**kw) -> MeshConfig:
    base = dict(resolution=0.1, crop_m=4.0, epochs=3, render_scale=1.0, eval_scale=1.0, pixels_per_step=512,
                holdout_every=3, device="cpu", threads=1, resume=False,
                view_range_m=0.0)  # the unit scene: road statistics around its trajectory only
    base.update(kw)
    return MeshConfig(**base)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return read_scene(tmp_path_factory.mktemp("mesh") / "seq", frames=6, width=48, height=32)


def test_grid_crop_counts():
    traj = np.array([[0.0, 0.0], [10.0, 0.0]])
    g = build_grid(traj, 0.1, 2.0)
    X, Y = g.spec.centres()
    dist = np.where((X >= 0) & (X <= 10), np.abs(Y), np.hypot(np.minimum(np.abs(X), np.abs(X - 10)), Y))
    assert (g.valid[dist <= 1.99]).all() and not g.valid[dist >= 2.1].any()
    assert abs(g.vertices - (10 * 4 + np.pi * 4) / 0.01) / g.vertices < 0.03
    v = g.valid
    assert g.faces == 2 * (v[:-1, :-1] & v[1:, 1:] & v[:-1, 1:] & v[1:, :-1]).sum() + \
        ((v[:-1, :-1] & v[1:, 1:]) & (v[:-1, 1:] ^ v[1:, :-1])).sum()
    one = build_grid(np.array([[5.0, 5.0]]), 0.1, 1.0)  # a one-frame trajectory: a disc
    assert abs(one.vertices - np.pi * 1.05**2 / 0.01) / one.vertices < 0.05  # crop + half-cell slack


def test_grid_covers_the_road_the_end_frames_look_at():
    """Issue 12 item 4: a forward camera at the last frame sees road 20-40 m past the trajectory's end."""
    from pavemap.mesh.setup import view_paths
    from pavemap.types import View

    traj = np.array([[0.0, 0.0], [10.0, 0.0]])
    T = np.eye(4)
    T[:3, :3] = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], dtype=float)  # camera +z = world +x (forward)
    T[:3, 3] = [10.0, 0.0, 1.6]
    down = T.copy()
    down[:3, :3] = np.array([[0, 0, 0.2], [-1, 0, 0], [0, -1, -0.98]], dtype=float)  # looking at its feet
    side = T.copy()
    side[:3, :3] = np.array([[1, 0, 0], [0, 0, 1], [0, -1, 0]], dtype=float)  # camera +z = world +y (left)
    back = T.copy()
    back[:3, :3] = np.array([[0, 0, -1], [1, 0, 0], [0, -1, 0]], dtype=float)  # camera +z = world -x
    last = [(-1, View(n, "x.png", m)) for n, m in (("front", T), ("down", down), ("left", side), ("back", back))]
    paths = view_paths(last, traj, 30.0)
    # only the camera looking out of the path's end: not the one at its feet, nor a surround rig's side
    # and back cameras (whose road the crop already holds; their axes would pull the mesh into buildings)
    assert len(paths) == 1 and np.allclose(paths[0], [[10.0, 0.0], [40.0, 0.0]])
    first_back = back.copy()
    first_back[:3, 3] = [0.0, 0.0, 1.6]
    assert np.allclose(view_paths([(0, View("back", "b.png", first_back))], traj, 30.0)[0], [[0, 0], [-30, 0]])
    g = build_grid(traj, 0.1, 2.0, paths)
    X, Y = g.spec.centres()
    ahead = (X > 20) & (X < 39) & (np.abs(Y) < 1.9)
    assert ahead.any() and g.valid[ahead].all() and not g.valid[(X > 42.2)].any()
    assert not g.valid[np.abs(Y) > 2.2].any()  # nothing sideways
    assert not build_grid(traj, 0.1, 2.0).valid.shape[1] > 150  # without it: the trajectory's crop only
    assert view_paths(last, traj, 0.0) == []


def test_height_mlp_matches_spec():
    for L in (4, 5):
        p = torch.rand(7, 2) * 2 - 1
        phi = positional_encoding(p, L)
        assert phi.shape == (7, 4 * L + 2)
        assert torch.allclose(phi[:, 2:4], torch.sin(np.pi * p)) and torch.allclose(phi[:, 4:6], torch.cos(np.pi * p))
        m = HeightMLP(L)
        lin0 = [x for x in m.mlp0 if isinstance(x, torch.nn.Linear)]
        lin1 = [x for x in m.mlp1 if isinstance(x, torch.nn.Linear)]
        assert [(x.in_features, x.out_features) for x in lin0] == [(4 * L + 2, 128)] + [(128, 128)] * 3
        assert [(x.in_features, x.out_features) for x in lin1] == [(4 * L + 2 + 128, 128)] + [(128, 128)] * 2 + [
            (128, 1)]
        assert m(p).shape == (7,)


def test_split_frames():
    train, held = split_frames(10, 5, 1)
    assert held == [2, 7] and set(train) | set(held) == set(range(10)) and not set(train) & set(held)
    train, held = split_frames(10, 5, 2)
    assert train == [0, 3, 5, 8] and held == [2, 7]
    assert split_frames(1, 5, 1) == ([0], [])
    with pytest.raises(PavemapError):
        MeshConfig.preset("waymo")
    assert MeshConfig.preset("kitti").crop_m == 5.0 and MeshConfig.preset("kitti").pe_levels == 4


def test_reconstruct_outputs_and_resume(scene, tmp_path):
    out = tmp_path / "out"
    mesh, m = reconstruct(scene, out, _cfg(epochs=2), progress=False)
    for f in ("mesh.ply", "mesh.npz", "bev_rgb.png", "bev_semantic.png", "bev_height.png", "bev_height.npy",
              "bev_rgb.npy", "bev_semantic.npy", "curves.png", "metrics.json", "checkpoint.pt", "grid.json"):
        assert (out / f).is_file(), f
    mj = json.loads((out / "metrics.json").read_text())
    for k in ("psnr", "sem_acc", "height_rmse", "seconds", "vertices", "faces", "device", "history"):
        assert k in mj
    assert len(mj["history"]) == 2 and mj["heldout"] and mj["device"] == "cpu"
    h = m["history"]
    assert h[-1]["loss"] < h[0]["loss"] and h[-1]["eval_psnr"] > h[0]["eval_psnr"]
    assert m["psnr"] > h[0]["eval_psnr"] + 1.0 and m["sem_acc"] > 0.8 and m["height_rmse"] < 0.2
    # the PLY is in world coordinates, vertex colours included, no hidden offset
    tm = trimesh.load(out / "mesh.ply", process=False)
    s = mesh.surface
    assert len(tm.vertices) == m["vertices"] == int(s.valid.sum()) and len(tm.faces) == m["faces"]
    assert np.allclose(tm.vertices, s.vertices()[s.valid.reshape(-1)].double().numpy(), atol=1e-4)
    assert tm.visual.vertex_colors.shape == (m["vertices"], 4)
    assert np.isfinite(np.load(out / "bev_height.npy")[s.valid.numpy()]).all()
    # load_mesh round trip and rendering a held-out view from it
    m2 = load_mesh(out)
    assert torch.allclose(m2.surface.heights, s.heights) and torch.allclose(m2.rgb, mesh.rgb)
    assert torch.equal(m2.contested, mesh.contested) and "texture_check" in mj  # the texture check, kept
    assert np.array_equal(np.load(out / "bev_contested.npy"), mesh.contested.numpy() & s.valid.numpy())
    assert m2.class_ids == [c.id for c in scene.classes]
    v = scene.frames[1].views["CAM0"]
    r = render_view(m2, scene.cameras["CAM0"], v.T_world_cam, scale=0.5)
    assert r["valid"].float().mean() > 0.3 and torch.isfinite(r["rgb"]).all()
    # resume: a 3-epoch run over the checkpoint trains only the third epoch and keeps the first two
    _, m3 = reconstruct(scene, out, _cfg(epochs=3, resume=True), progress=False)
    assert len(m3["history"]) == 3 and m3["history"][:2] == h


def test_deterministic(scene):
    a, _ = reconstruct(scene, None, _cfg(epochs=1), progress=False)
    b, _ = reconstruct(scene, None, _cfg(epochs=1), progress=False)
    assert torch.equal(a.surface.heights, b.surface.heights) and torch.equal(a.rgb, b.rgb)


def test_no_semantics_one_frame_nan_pose(tmp_path):
    seq = make_scene(tmp_path / "ns", frames=3, width=32, height=20, semantics=False, cams=(0.0, 180.0))
    with pytest.warns(UserWarning, match="no semantic maps"):
        mesh, m = reconstruct(seq, None, _cfg(epochs=1), progress=False)
    assert not mesh.has_semantics and m["sem_acc"] is None
    assert torch.equal(mesh.road_mask(seq.classes), mesh.surface.valid)
    one = copy.deepcopy(seq)
    one.frames = one.frames[:1]
    with pytest.warns(UserWarning, match="fewer than 2 frames"):
        mesh, m = reconstruct(one, None, _cfg(epochs=1), progress=False)
    assert torch.isfinite(mesh.surface.heights).all() and not m["heldout"]
    bad = copy.deepcopy(seq)
    bad.frames[0].views["CAM1"].T_world_cam = np.full((4, 4), np.nan)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        mesh, m = reconstruct(bad, None, _cfg(epochs=1), progress=False)
    assert any("NaN" in str(w.message) for w in caught)
    assert torch.isfinite(mesh.surface.heights).all() and torch.isfinite(mesh.rgb).all()


def test_sky_cameras_fail_clearly(tmp_path):
    seq = make_scene(tmp_path / "sky", frames=2, width=24, height=16, cams=(0.0,))
    for f in seq.frames:
        for v in f.views.values():
            v.T_world_cam = look(v.T_world_cam[:3, 3], 0.0, -50.0)  # pitched 50 degrees up: only sky
    with pytest.raises(PavemapError, match="no training view sees the road"):
        reconstruct(seq, None, _cfg(epochs=1), progress=False)


@pytest.fixture(scope="module")
def depth_scene(tmp_path_factory):
    return read_scene(tmp_path_factory.mktemp("meshd") / "seq", frames=6, width=48, height=32, depth_every=2)


def test_pose_refinement_recovers_perturbation(depth_scene):
    """A known 0.3 deg / 0.2 m perturbation of every view (with LiDAR-like depth, as the synthetic world has)."""
    pert, truth = perturb_poses(depth_scene, 0.3, 0.2, seed=3)
    raw = {k: v.T_world_cam for f in pert.frames for k, v in ((f"{f.index}/{n}", v) for n, v in f.views.items())}
    cfg = _cfg(epochs=4, pixels_per_step=512, holdout_every=0, pose_refine=True, pose_per="view")
    _, m = reconstruct(pert, None, cfg, progress=False)
    before = pose_errors({k: raw[k] for k in m["refined_poses"]}, truth)
    after = pose_errors(m["refined_poses"], truth)
    assert before["trans_mean_m"] == pytest.approx(0.2) and before["rot_mean_deg"] == pytest.approx(0.3)
    print(before, after)
    assert after["rot_mean_deg"] < before["rot_mean_deg"], (after, before)
    assert after["trans_mean_m"] < 0.7 * before["trans_mean_m"], (after, before)
    assert all(r["cost_last"] < r["cost_first"] for r in m["pose_alignment"])
    _, m0 = reconstruct(pert, None, _cfg(epochs=4, pixels_per_step=512, holdout_every=0), progress=False)
    assert m["psnr"] > m0["psnr"] + 3.0, (m["psnr"], m0["psnr"])


def test_depth_samples_keep_returns_on_their_own_rays():
    """Sparse depth downscaled: every target pixel holding a return keeps one, and its uv is that
    return's exact position in the scaled camera (so its ray is the LiDAR return's ray)."""
    from pavemap.mesh.data import _depth_samples
    from pavemap.types import Camera

    rng = np.random.default_rng(0)
    H, W, s = 40, 64, 0.25
    dep = np.zeros((H, W), np.float32)
    ys, xs = rng.integers(0, H, 60), rng.integers(0, W, 60)
    dep[ys, xs] = rng.uniform(2, 30, 60).astype(np.float32)
    cam = Camera("c", W, H, np.array([[50.0, 0, 31.5], [0, 50.0, 19.5], [0, 0, 1]]))
    small = cam.scaled(s)
    out, uv = _depth_samples(dep, (small.width, small.height), s)
    ty, tx = np.nonzero(out)
    # as many target pixels with depth as distinct target pixels the returns fall in
    key = np.unique(np.clip(np.rint(s * (np.nonzero(dep)[0] + 0.5) - 0.5), 0, small.height - 1) * small.width
                    + np.clip(np.rint(s * (np.nonzero(dep)[1] + 0.5) - 0.5), 0, small.width - 1))
    assert ty.size == key.size > 10
    # each kept depth sits on its source ray: back to source pixel coordinates it lands on a return
    u_src = (uv[ty, tx, 0] + 0.5) / s - 0.5
    v_src = (uv[ty, tx, 1] + 0.5) / s - 0.5
    np.testing.assert_allclose(u_src, np.rint(u_src), atol=1e-4)
    np.testing.assert_allclose(v_src, np.rint(v_src), atol=1e-4)
    np.testing.assert_array_equal(dep[np.rint(v_src).astype(int), np.rint(u_src).astype(int)], out[ty, tx])
    # the scaled intrinsics map the source pixel's ray to that uv
    ray = np.linalg.inv(cam.K) @ np.stack([np.rint(u_src), np.rint(v_src), np.ones_like(u_src)])
    proj = small.K @ ray
    np.testing.assert_allclose(proj[:2] / proj[2], np.stack([uv[ty, tx, 0], uv[ty, tx, 1]]), atol=1e-3)
    # pixels without a return keep their integer centre
    empty = out == 0
    np.testing.assert_array_equal(uv[empty][:, 0], np.nonzero(empty)[1])


def test_ground_continues_the_grade_beyond_the_trajectory_ends():
    from pavemap.mesh.init_surface import idw_ground

    traj = np.stack([np.linspace(0.0, 20.0, 21), np.zeros(21)], 1)
    ground = 0.05 * traj[:, 0]  # a 5 % climb
    beyond = np.array([[-4.0, 0.0], [-4.0, 3.0], [24.0, -1.0]])
    at_end = np.array([[0.0, 0.0], [0.0, 3.0], [20.0, -1.0]])
    np.testing.assert_allclose(idw_ground(traj, ground, beyond) - idw_ground(traj, ground, at_end), [-0.2, -0.2, 0.2],
                               atol=1e-5)
    np.testing.assert_allclose(idw_ground(traj, ground, np.array([[10.0, 0.0]])), 0.5, atol=0.02)  # inside: IDW
    flat = idw_ground(traj[:1], ground[:1], beyond)  # one frame: nothing to extrapolate
    np.testing.assert_allclose(flat, 0.0)


def test_ground_of_another_pass_is_not_this_pass_continued():
    """A segment of a long drive holds two passes: one climbing east that ends at x = 50, one crossing north at
    x = 100 on level ground. The road of the second pass lies beyond the first one's end, but it is not the
    first road continued: it keeps its own height (the old extrapolation put it 2.5 m high)."""
    from pavemap.mesh.init_surface import idw_ground

    east = np.stack([np.linspace(0.0, 50.0, 51), np.zeros(51)], 1)
    north = np.stack([np.full(41, 100.0), np.linspace(-20.0, 20.0, 41)], 1)
    traj = np.concatenate([north, east])  # the segment's last frame is the east pass's end, facing north's road
    ground = np.concatenate([np.full(41, 1.0), 0.05 * east[:, 0]])
    on_north = np.array([[100.0, 0.0], [102.0, 10.0], [98.0, -15.0]])
    np.testing.assert_allclose(idw_ground(traj, ground, on_north), 1.0, atol=1e-5)
    # beyond the north pass's far end its own (level) grade continues; beyond the east pass's start, its climb
    beyond, at_end = np.array([[100.0, 30.0], [-4.0, 0.0]]), np.array([[100.0, 20.0], [0.0, 0.0]])
    np.testing.assert_allclose(idw_ground(traj, ground, beyond) - idw_ground(traj, ground, at_end), [0.0, -0.2],
                               atol=1e-5)


def test_road_coordinates_and_relief_follow_each_pass():
    """Road coordinates never run along the jump between two passes, and the relief is fitted per pass: a
    kerb-high (0.12 m) step measured on one pass does not leak onto the other."""
    from pavemap.mesh.init_surface import PASS_GAP_S, road_relief, track_coords

    east = np.stack([np.linspace(0.0, 60.0, 61), np.zeros(61)], 1)
    north = np.stack([np.full(61, 200.0), np.linspace(0.0, 60.0, 61)], 1)
    traj = np.concatenate([east, north])
    k, s, l = track_coords(traj, np.array([[30.0, 2.0], [199.0, 30.0], [120.0, 0.0]]))
    np.testing.assert_array_equal(k, [0, 1, 0])  # the point half way along the jump belongs to the nearer end
    np.testing.assert_allclose(s[:2], [30.0, 60.0 + PASS_GAP_S + 30.0], atol=1e-6)
    np.testing.assert_allclose(l[:2], [2.0, 1.0], atol=1e-6)
    rng = np.random.default_rng(0)
    pts = np.concatenate([np.stack([rng.uniform(0, 60, 800), rng.uniform(-5, 5, 800)], 1),
                          np.stack([rng.uniform(195, 205, 800), rng.uniform(0, 60, 800)], 1)])
    r = np.where(pts[:, 0] < 100.0, 0.12, 0.0)
    q = np.array([[30.0, 0.0], [200.0, 30.0]])
    np.testing.assert_allclose(road_relief(traj, pts, r, q), [0.12, 0.0], atol=0.01)
    assert road_relief(traj, pts[:50], r[:50], q) is None  # too few points on every pass


def test_pose_refinement_per_frame_moves_the_rig_as_one(depth_scene):
    """An ego-pose error (all cameras of a frame moved rigidly together) refined with one correction per frame:
    the cameras stay rigid relative to each other and the error shrinks."""
    pert, truth = perturb_poses(depth_scene, 0.3, 0.2, seed=4, per="frame")
    raw = {f"{f.index}/{n}": v.T_world_cam for f in pert.frames for n, v in f.views.items()}
    _, m = reconstruct(pert, None, _cfg(epochs=2, pixels_per_step=512, holdout_every=0, pose_refine=True,
                                        pose_per="frame"), progress=False)
    before = pose_errors({k: raw[k] for k in m["refined_poses"]}, truth)
    after = pose_errors(m["refined_poses"], truth)
    assert after["trans_mean_m"] < 0.7 * before["trans_mean_m"], (after, before)
    # rigid rig: camera-to-camera transforms within each frame are unchanged by the correction
    for f in pert.frames:
        keys = [f"{f.index}/{n}" for n in f.views]
        Ta, Tb = np.array(m["refined_poses"][keys[0]]), np.array(m["refined_poses"][keys[1]])
        np.testing.assert_allclose(np.linalg.inv(Ta) @ Tb, np.linalg.inv(raw[keys[0]]) @ raw[keys[1]], atol=1e-4)


def test_unmeasured_ground_takes_the_cross_section_from_along_the_road():
    """A patch of sidewalk no point reaches (behind a parked car) gets the sidewalk's height from before and
    after it along the road, not a blend with the road 0.12 m below."""
    from pavemap.mesh.init_surface import along_track, fill_along_track

    traj = np.stack([np.linspace(0.0, 30.0, 31), np.zeros(31)], 1)
    X, Y = np.meshgrid(np.arange(0.0, 30.0, 0.1), np.arange(-5.0, 5.0, 0.1))
    xy = np.stack([X.reshape(-1), Y.reshape(-1)], 1)
    truth = np.where(xy[:, 1] < -3.0, 0.12, 0.0)  # sidewalk right of the road
    measured = ~((xy[:, 0] > 12) & (xy[:, 0] < 16) & (xy[:, 1] < -2.5))  # a car hides 4 m of curb and sidewalk
    s, l = along_track(traj, xy)
    np.testing.assert_allclose(s, xy[:, 0], atol=1e-6)
    np.testing.assert_allclose(l, xy[:, 1], atol=1e-6)
    filled = fill_along_track(np.where(measured, truth, 0.0), measured, s, l, sigma_s=4.0)
    hidden = ~measured
    err = np.abs(filled - truth)
    away = hidden & (np.abs(xy[:, 1] + 3.0) > 0.25)  # the step itself is smoothed over +-0.1 m across
    assert err[away].max() < 0.01 and err[hidden].mean() < 0.01, (err[away].max(), err[hidden].mean())


def test_a_non_finite_sparse_gradient_skips_the_step():
    """The per-vertex colours' gradients are sparse and checked uncoalesced: a NaN among them still stops the step."""
    from types import SimpleNamespace

    from pavemap.mesh.config import MeshConfig
    from pavemap.mesh.step import MultiOptimizer, NonFiniteStepError, _update

    emb = torch.nn.Parameter(torch.ones(5, 3))
    fit = SimpleNamespace(cfg=MeshConfig(), opt=MultiOptimizer(torch.optim.SparseAdam([emb], lr=0.1)), params=[emb])
    idx = torch.tensor([[0, 1, 1], [2, 2, 3]])  # row 1 and row 2 twice: an uncoalesced gradient
    loss = (torch.nn.functional.embedding(idx, emb, sparse=True) - 1).abs().sqrt().sum()  # 0, d/dx: 0 * inf
    assert float(loss) == 0.0
    with pytest.raises(NonFiniteStepError, match="gradients"):
        _update(fit, loss, 0.5)
    assert torch.equal(emb.detach(), torch.ones(5, 3)) and emb.grad is None
    ok = (torch.nn.functional.embedding(idx, emb, sparse=True) ** 2).sum()
    _update(fit, ok, 0.5)
    assert not torch.equal(emb.detach(), torch.ones(5, 3)) and torch.equal(emb.detach()[4], torch.ones(3))
