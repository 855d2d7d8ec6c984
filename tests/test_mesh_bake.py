"""Closed-form colour baking (pavemap.mesh.bake) on the tiny textured scene with its true surface."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from mesh_scene import read_scene, texture, truth_field
from pavemap.geometry import HeightField
from pavemap.mesh import MeshConfig, reconstruct
from pavemap.mesh.bake import bake_colours
from pavemap.mesh.data import build_pool, finite_views
from pavemap.mesh.model import build_grid


@pytest.fixture(scope="module")
def seq(tmp_path_factory):
    return read_scene(tmp_path_factory.mktemp("bake") / "seq", frames=6, width=64, height=40)


def _true_surface(seq, res: float = 0.1):
    traj = np.array([np.mean([v.T_world_cam[:3, 3] for v in f.views.values()], 0) for f in seq.frames])
    g = build_grid(traj[:, :2], res, 4.0)
    X, Y = g.spec.centres()
    xy = np.stack([X, Y], -1).reshape(-1, 2)
    z, _ = truth_field().height_at(torch.tensor(xy))
    return g, xy, z.float().reshape(g.spec.shape)


def _field(g, heights: torch.Tensor) -> HeightField:
    s = g.spec
    return HeightField(s.x0, s.y0, s.res, heights, torch.from_numpy(g.valid.copy()))


def _all_views_pool(seq):
    """The pool of every view at full scale (no depth)."""
    lut = np.full(256, -1, dtype=np.int64)
    for ch, c in enumerate(seq.classes):
        lut[c.id] = ch
    views, _ = finite_views(seq, list(range(len(seq.frames))))
    return build_pool(seq, views, 1.0, lut, True, False)


def test_baked_colours_match_the_texture(seq):
    g, xy, heights = _true_surface(seq)
    pool = _all_views_pool(seq)
    valid = torch.from_numpy(g.valid.copy())
    rgb, support, coloured = bake_colours(_field(g, heights), pool, pool.T, 60.0)
    assert rgb.shape == (*g.spec.shape, 3) and support.shape == g.spec.shape
    assert torch.isfinite(rgb).all() and (rgb >= 0).all() and (rgb <= 1).all()
    # well-observed vertices carry the texture's colour there (a pixel averages ~0.1 m of texture)
    tex = torch.from_numpy(texture(xy).reshape(*g.spec.shape, 3)).float()
    seen = (support > 2.0) & valid
    assert seen.sum() > 500
    err = (rgb - tex).abs().mean(-1)[seen]
    assert float(err.median()) < 0.03, float(err.median())
    # seen vertices are coloured; unseen ones next to them get their neighbours' colour; far from any view
    # nothing is coloured and the colour is 0 (the caller keeps its own values there)
    assert (support >= 0).all() and coloured[support > 0].all()
    filled = coloured & (support == 0)
    assert filled.any() and (rgb[filled].sum(-1) > 0).all()
    assert (rgb[~coloured] == 0).all()


def test_bake_fills_isolated_gaps():
    """A vertex no pixel reaches, among seen ones, takes its neighbours' colour, not 0."""
    from pavemap.mesh.data import PixelPool, ViewKey

    # One camera looking straight down at a flat, uniformly grey plane; the vertex under the optical axis is
    # reached by no pixel ray centre when pixels are sparser than vertices.
    K = torch.tensor([[20.0, 0, 3.5], [0, 20.0, 3.5], [0, 0, 1]])
    T = torch.eye(4)
    T[:3, :3] = torch.tensor([[1.0, 0, 0], [0, -1.0, 0], [0, 0, -1.0]])  # z axis pointing down
    T[2, 3] = 10.0
    yy, xx = torch.meshgrid(torch.arange(8.0), torch.arange(8.0), indexing="ij")
    uv = torch.stack([xx.reshape(-1), yy.reshape(-1)], 1)
    n = uv.shape[0]
    pool = PixelPool([ViewKey(0, "c")], K[None], T[None], torch.zeros(n, dtype=torch.long), uv,
                     torch.full((n, 3), 128, dtype=torch.uint8), torch.full((n,), -1, dtype=torch.long),
                     torch.ones(n, dtype=torch.bool), None)
    res = 0.1  # pixel footprint at 10 m: 0.5 m, so most vertices get no pixel
    hf = HeightField.plane(-2.0, -2.0, res, 41, 41, 0.0)
    rgb, support, coloured = bake_colours(hf, pool, pool.T, 60.0, fill_sigma=3.0)
    inner = coloured[12:28, 12:28]
    assert inner.all() and (support[12:28, 12:28] == 0).any()  # some inner vertices were filled, not seen
    np.testing.assert_allclose(rgb[12:28, 12:28].numpy(), 128 / 255.0, atol=1e-5)


def test_reconstruction_with_baking_beats_adam_alone(seq):
    base = dict(resolution=0.1, crop_m=4.0, epochs=2, render_scale=1.0, eval_scale=1.0, pixels_per_step=512,
                holdout_every=3, device="cpu", threads=1, resume=False)
    _, m_bake = reconstruct(seq, None, MeshConfig(**base), progress=False)
    _, m_adam = reconstruct(seq, None, MeshConfig(**base, bake_init=False, bake_final=False), progress=False)
    assert m_bake["psnr"] > m_adam["psnr"] + 1.0, (m_bake["psnr"], m_adam["psnr"])


def test_ground_classes():
    from pavemap.types import SemanticClass

    ground = ["road", "curb", "flat.sidewalk", "flat.driveable_surface", "Terrain", "lane-marking"]
    assert all(SemanticClass(0, n, road=(n == "road")).ground for n in ground)
    assert not any(SemanticClass(0, n).ground for n in ["building", "vehicle.car", "static.vegetation", "pole"])


def test_depth_relief_keeps_the_curb_and_ignores_objects(tmp_path):
    """The initial surface from measured depth: the 0.12 m curb stays a step with the fine bins, and depth on
    a non-ground class (the parked vehicle) is dropped from the pool."""
    from mesh_scene import CURB, ROAD_HALF
    from pavemap.mesh.init_surface import depth_points, depth_relief, ground_under_trajectory

    seq = read_scene(tmp_path / "d", frames=6, width=64, height=40, depth_every=1)
    lut = np.full(256, -1, dtype=np.int64)
    for ch, c in enumerate(seq.classes):
        lut[c.id] = ch
    views, _ = finite_views(seq, list(range(len(seq.frames))))
    pool = build_pool(seq, views, 1.0, lut, True, True)
    ground_ids = torch.tensor([c.id for c in seq.classes if c.ground])
    lab_of_channel = torch.tensor([c.id for c in seq.classes])
    has = pool.depth > 0
    assert has.sum() > 1000 and torch.isin(lab_of_channel[pool.channel[has]], ground_ids).all()
    traj = np.array([np.mean([v.T_world_cam[:3, 3] for v in f.views.values()], 0) for f in seq.frames])
    g = build_grid(traj[:, :2], 0.1, 5.0)
    base = ground_under_trajectory(g, traj[:, :2], traj[:, 2] - 1.5)
    xy = g.vertex_xy()
    truth, _ = truth_field().height_at(torch.tensor(xy))
    truth = truth.numpy()

    def step(z):  # mean height just outside minus just inside the curb, where the drive passes
        x_ok = (xy[:, 0] > 1.0) & (xy[:, 0] < 5.0)
        outside = x_ok & (np.abs(np.abs(xy[:, 1]) - ROAD_HALF - 0.25) < 0.1)
        inside = x_ok & (np.abs(np.abs(xy[:, 1]) - ROAD_HALF + 0.25) < 0.1)
        return float(z[outside].mean() - z[inside].mean())

    pts = depth_points(pool)
    coarse = base + depth_relief(pts, g, traj, traj[:, 2] - 1.5, 1.0, fill_sigmas=(1.0, 2.0, 4.0))
    fine = base + depth_relief(pts, g, traj, traj[:, 2] - 1.5, 1.0, fine_cell=0.3, fill_sigmas=(1.0, 2.0, 4.0))
    assert step(truth) > CURB - 0.01
    assert step(fine) > 0.75 * step(truth) > step(coarse), (step(fine), step(truth), step(coarse))


def test_sharpened_bake_fits_pixels_better_and_stays_near_the_texture(seq):
    """Jacobi steps towards the least-squares colours lower the training residual step by step, keep unseen
    vertices' fill, and stay close to the true texture (no overfitting blow-up)."""
    from pavemap.geometry import find_hits, hits_to_rayhit
    from pavemap.mesh.render import view_rays

    g, xy, heights = _true_surface(seq)
    pool = _all_views_pool(seq)
    valid = torch.from_numpy(g.valid.copy())
    hf = _field(g, heights)
    o, d = view_rays(pool.K, pool.T, pool.view, pool.uv)
    hit = hits_to_rayhit(hf, o, d, find_hits(hf, o, d, 60.0))
    gt = pool.rgb[hit.hit].float() / 255.0
    tex = torch.from_numpy(texture(xy).reshape(*g.spec.shape, 3)).float()
    mse, tex_err = [], []
    for k in (0, 1, 2):
        rgb, support, coloured = bake_colours(hf, pool, pool.T, 60.0, sharpen_iters=k)
        pred = hit.interpolate(rgb.reshape(-1, 3))[hit.hit]
        mse.append(float(((pred - gt) ** 2).mean()))
        tex_err.append(float((rgb - tex).abs().mean(-1)[(support > 2.0) & valid].median()))
        assert coloured[support > 0].all() and (rgb >= 0).all() and (rgb <= 1).all()
    assert mse[0] > mse[1] > mse[2], mse
    assert max(tex_err) < 0.03, tex_err


def test_pixels_of_a_passing_vehicle_are_left_out(seq):
    """A 'vehicle' painted into one view's road pixels disagrees with the road the other views see."""
    import dataclasses

    from pavemap.mesh.bake import pixel_residuals, static_pixels

    g, _, heights = _true_surface(seq)
    pool = _all_views_pool(seq)
    surf = _field(g, heights)
    r = pixel_residuals(surf, pool, pool.T, 60.0, bake_colours(surf, pool, pool.T, 60.0)[0])
    hits = torch.isfinite(r)
    assert hits.float().mean() > 0.3 and float(r[hits].median()) < 0.05  # rays that land: the road's colour
    car = (pool.view == 2) & pool.road & hits
    car[torch.nonzero(car).squeeze(1)[car.sum() // 3:]] = False  # a third of that view's road on the mesh
    painted = dataclasses.replace(pool, rgb=torch.where(car[:, None], torch.tensor([200, 20, 20], dtype=torch.uint8),
                                                        pool.rgb))
    keep = static_pixels(surf, painted, painted.T, 60.0, cutoff=0.25)
    # most of the vehicle's pixels go (not those on road only that view saw: there it is the majority) ...
    assert car.sum() > 20 and (~keep[car]).float().mean() > 0.5
    assert keep[~car].float().mean() > 0.98  # ... and the road stays
    # the texture under the vehicle is road again once its pixels are left out
    clean = bake_colours(surf, pool, pool.T, 60.0)[0]
    on_car = pixel_residuals(surf, painted.subset(car), painted.T, 60.0, clean) > 0.25
    before = bake_colours(surf, painted, painted.T, 60.0)[0]
    after = bake_colours(surf, painted.subset(keep), painted.T, 60.0)[0]
    red = lambda t: float((t[..., 0] - t[..., 1]).mean())  # noqa: E731
    assert on_car.all() and red(after) < red(before)


def test_initial_bake_reusing_the_visible_pixel_march_changes_nothing(seq, monkeypatch):
    """The initial bake takes the march visible_pixels made on the same surface: the same mesh as marching
    again, to the bit (and the march is really reused: one march fewer)."""
    import pavemap.mesh.bake as bake
    import pavemap.mesh.train as train

    cfg = dict(resolution=0.1, crop_m=4.0, epochs=1, render_scale=1.0, eval_scale=1.0, pixels_per_step=512,
               holdout_every=3, device="cpu", threads=1, resume=False)
    marches = []
    real_march = bake.march_pool
    monkeypatch.setattr(bake, "march_pool", lambda *a, **k: marches.append(1) or real_march(*a, **k))
    mesh_reused, _ = reconstruct(seq, None, MeshConfig(**cfg), progress=False)
    reused = len(marches)
    real_visible = train.visible_pixels
    monkeypatch.setattr(train, "visible_pixels", lambda *a, **k: real_visible(*a, **{**k, "keep_hits": False}))
    mesh_again, _ = reconstruct(seq, None, MeshConfig(**cfg), progress=False)
    assert len(marches) - reused == reused + 1  # the initial bake marched again (the final bake always does)
    assert torch.equal(mesh_reused.rgb, mesh_again.rgb)
    assert torch.equal(mesh_reused.surface.heights, mesh_again.surface.heights)


def test_the_visible_pixel_march_keeps_each_hits_row_in_the_thinned_pool(seq, monkeypatch):
    """visible_pixels drops the pixels that miss the mesh and keeps its march: each hit's ``rows`` then point
    at its own pixel in the thinned pool (what the texture check reads)."""
    import pavemap.mesh.train as train

    got = []
    real = train.visible_pixels

    def spy(model, pool, *a, **k):  # noqa: ANN001, ANN202
        thinned, hits = real(model, pool, *a, **k)
        got.append((len(pool), thinned, hits))
        return thinned, hits

    monkeypatch.setattr(train, "visible_pixels", spy)
    reconstruct(seq, None, MeshConfig(resolution=0.1, crop_m=4.0, epochs=0, render_scale=1.0, eval_scale=1.0,
                                      holdout_every=3, device="cpu", threads=1, resume=False), progress=False)
    before, pool, hits = got[0]
    assert hits and len(pool) < before  # some pixels missed: the rows were renumbered
    rows = torch.cat([h.rows for h in hits])
    assert torch.equal(pool.rgb[rows], torch.cat([h.c8 for h in hits]))
    assert torch.equal(pool.view[rows], torch.cat([h.view for h in hits])) and len(torch.unique(rows)) == len(rows)


def test_texture_check_takes_the_final_bake_march_and_changes_nothing(seq, monkeypatch, tmp_path):
    """The texture check reads the final bake's march (no march of its own) and leaves the mesh as it is, to
    the bit; with the moving-pixel rejection on it checks every pixel, the dropped ones too (its own march)."""
    import pavemap.mesh.texture_check as texture_check

    cfg = dict(resolution=0.1, crop_m=4.0, epochs=0, render_scale=1.0, eval_scale=1.0, holdout_every=3,
               device="cpu", threads=1, resume=False)
    own = []
    real_march = texture_check.march_pool
    monkeypatch.setattr(texture_check, "march_pool", lambda *a, **k: own.append(1) or real_march(*a, **k))
    checked, m = reconstruct(seq, None, MeshConfig(**cfg), progress=False)
    plain, m_plain = reconstruct(seq, None, MeshConfig(**cfg, texture_check=False), progress=False)
    assert own == [] and "texture_check" in m and "texture_check" not in m_plain
    assert checked.contested is not None and plain.contested is None
    from pavemap.mesh import write_outputs

    write_outputs(tmp_path / "plain", plain, m_plain, seq.classes)  # not checked is not clean: no raster
    write_outputs(tmp_path / "checked", checked, m, seq.classes)
    assert not (tmp_path / "plain" / "bev_contested.npy").exists()
    assert (tmp_path / "checked" / "bev_contested.npy").is_file()
    assert torch.equal(checked.rgb, plain.rgb) and torch.equal(checked.surface.heights, plain.surface.heights)
    reconstruct(seq, None, MeshConfig(**cfg, moving_cutoff=0.01, moving_blob_px=0), progress=False)
    assert own == [1]


def test_semantic_bake_takes_each_vertex_majority_of_weighted_votes():
    """Closed-form logits: the barycentric-weighted class votes of the labelled pixels; unlabelled pixels
    (channel -1) do not vote and a vertex no labelled pixel reaches is not reported as labelled."""
    from pavemap.mesh.bake import Hits, bake_semantics

    vid = torch.tensor([[0, 1, 2]] * 5 + [[0, 1, 2]])
    w = torch.tensor([[0.8, 0.2, 0.0]] * 3 + [[0.1, 0.9, 0.0]] * 2 + [[0.0, 0.0, 1.0]])
    channel = torch.tensor([2, 2, 2, 0, 0, -1])
    hits = [Hits(vid, w, torch.zeros(6, 3, dtype=torch.uint8), torch.zeros(6, dtype=torch.long), channel)]
    logits, labelled = bake_semantics(hits, 4, 3)
    assert logits.shape == (4, 3) and torch.isfinite(logits).all()
    assert labelled.tolist() == [True, True, False, False]  # vertex 2: only the unlabelled pixel; 3: none
    assert logits[0].argmax() == 2 and logits[1].argmax() == 0  # 2.4 vs 0.2 votes; 1.8 vs 0.6
    p = logits[0].exp()
    assert torch.isclose(p.sum(), torch.tensor(1.0)) and 0.5 < float(p[2]) < 1.0  # the prior: never certain


def test_initial_semantic_bake_labels_the_mesh_without_training(seq):
    """With no training step the mesh's semantics come from the initial bake alone (before it, zero logits:
    every vertex the first class) and agree with the held-out views' labels."""
    cfg = dict(resolution=0.1, crop_m=4.0, epochs=0, render_scale=1.0, eval_scale=1.0, holdout_every=3,
               device="cpu", threads=1, resume=False)
    mesh, m = reconstruct(seq, None, MeshConfig(**cfg), progress=False)
    assert len(set(mesh.sem_logits.argmax(-1).tolist())) > 1
    assert m["sem_acc"] > 0.9, m["sem_acc"]


def test_a_hit_a_hair_outside_its_triangle_votes_nothing_against_a_vertex():
    """Barycentric weights of -0.003 (rounding at a triangle's edge, seen on KITTI-00) once left a vertex whose
    only votes summed to ~0 with a colour of 1e6 and broke the views' exposure fit; the hits now carry none."""
    from pavemap.geometry import hits_to_rayhit
    from pavemap.geometry.heightfield import HitCells
    from pavemap.mesh.bake import _mean_colours, batch_hits
    from pavemap.mesh.data import PixelPool, ViewKey

    hf = HeightField.plane(0.0, 0.0, 1.0, 3, 3, 0.0)
    # two rays straight down into cell (0, 0): one well inside its lower triangle, one 3 mm across the diagonal
    # but assigned to the upper triangle, as a march that rounds the other way would
    o = torch.tensor([[0.7, 0.2, 2.0], [0.503, 0.497, 2.0]], dtype=torch.float64)
    d = torch.tensor([[0.0, 0.0, -1.0], [0.0, 0.0, -1.0]], dtype=torch.float64)
    z = torch.zeros(2, dtype=torch.long)
    hit = hits_to_rayhit(hf, o, d, HitCells(torch.arange(2), torch.full((2,), 2.0, dtype=torch.float64), z, z,
                                            torch.tensor([True, False])))
    assert float(hit.bary.min()) >= 0 and torch.allclose(hit.bary.sum(1), torch.ones(2, dtype=torch.float64))
    stray = int(hit.vertex_ids[1, 2])  # the upper triangle's third vertex, which the second hit lies beyond
    assert stray not in hit.vertex_ids[0].tolist() and float(hit.bary[1, 2]) == 0.0
    n = 2
    pool = PixelPool([ViewKey(0, "c")], torch.eye(3)[None], torch.eye(4)[None], torch.zeros(n, dtype=torch.long),
                     torch.zeros(n, 2), torch.tensor([[200, 200, 200], [100, 100, 100]], dtype=torch.uint8),
                     torch.full((n,), -1, dtype=torch.long), torch.ones(n, dtype=torch.bool), None)
    h = batch_hits(pool, slice(0, n), torch.arange(n), hit.vertex_ids, hit.bary)
    rgb, support = _mean_colours([h], hf.nx * hf.ny, None, torch.device("cpu"))
    assert float(support[stray]) == 0 and torch.isfinite(rgb).all() and float(rgb.abs().max()) <= 1.0


def test_only_blobs_of_disagreeing_pixels_are_taken_for_vehicles():
    """A thin line of disagreeing pixels (a paint edge a centimetre off) stays; a wide blob (a vehicle) goes."""
    from pavemap.mesh.bake import _opened
    from pavemap.mesh.data import PixelPool, ViewKey

    H, W = 20, 30
    v, u = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    uv = torch.stack([u.reshape(-1), v.reshape(-1)], 1).float() + 0.5
    n = H * W
    pool = PixelPool([ViewKey(0, "a")], torch.eye(3)[None], torch.eye(4)[None], torch.zeros(n, dtype=torch.long),
                     uv, torch.zeros(n, 3, dtype=torch.uint8), torch.full((n,), -1), torch.ones(n, dtype=torch.bool),
                     None)
    flag = torch.zeros(H, W, dtype=torch.bool)
    flag[3, :] = True  # a line one pixel wide
    flag[10:16, 5:12] = True  # a blob 6 x 7
    flag[12, 20:23] = True  # a speck
    out = _opened(flag.reshape(-1), pool, 2).reshape(H, W)
    assert out[10:16, 5:12].all()  # the blob stays whole
    assert not out[3].any() and not out[12, 20:23].any()  # the line and the speck go
    assert not (out & ~flag).any()


def test_texture_check_marks_where_a_vehicle_is_in_the_texture_and_nothing_on_a_clean_road(seq):
    """The final-texture check (pavemap.mesh.texture_check): a vehicle painted into four views' road pixels is
    baked into the texture; a patch of contested squares lies where it landed, the clean road has none."""
    import dataclasses

    from pavemap.mesh.bake import pixel_residuals
    from pavemap.mesh.texture_check import check_texture, contested_patches

    g, _, heights = _true_surface(seq)
    pool = _all_views_pool(seq)
    surf = _field(g, heights)

    def check(p):  # noqa: ANN001, ANN202
        rgb = bake_colours(surf, p, p.T, 60.0)[0]
        return check_texture(surf, p, p.T, 60.0, rgb, None, cutoff=0.15, blob_px=1, min_share=0.1, min_views=2,
                             block=5)

    clean = check(pool)
    assert torch.isfinite(clean.share).float().mean() > 0.5  # most of the crop is seen
    assert contested_patches(clean.contested.numpy(), g.spec.res, 1.0)[1] == []
    hits = torch.isfinite(pixel_residuals(surf, pool, pool.T, 60.0, bake_colours(surf, pool, pool.T, 60.0)[0]))
    car = torch.zeros(len(pool), dtype=torch.bool)
    for v in (1, 2, 3, 4):
        mine = torch.nonzero((pool.view == v) & pool.road & hits).squeeze(1)
        car[mine[: len(mine) // 2]] = True  # the far half of each view's road, a blob of rows
    painted = dataclasses.replace(pool, rgb=torch.where(car[:, None], torch.tensor([30, 40, 90], dtype=torch.uint8),
                                                        pool.rgb))
    got = check(painted)
    keep, patches = contested_patches(got.contested.numpy(), g.spec.res, 1.0)
    assert patches and patches[0]["area_m2"] >= 4.0 and int(got.views.max()) >= 2
    # the patch lies where the vehicle's pixels land (the squares they reach)
    under = torch.isfinite(check(painted.subset(car)).share).numpy()
    assert under[keep].mean() > 0.95
    # the same paint in one view only (a glare): fewer squares the more views are asked to disagree, and no
    # patch of 1 m² with the default 2
    solo = car & (pool.view == 2)
    one = dataclasses.replace(pool, rgb=torch.where(solo[:, None], torch.tensor([30, 40, 90], dtype=torch.uint8),
                                                    pool.rgb))
    rgb1 = bake_colours(surf, one, one.T, 60.0)[0]
    marked = [check_texture(surf, one, one.T, 60.0, rgb1, None, cutoff=0.15, blob_px=1, min_share=0.1,
                            min_views=k, block=5).contested.numpy() for k in (1, 2)]
    assert int(solo.sum()) > 100 and marked[0].sum() > marked[1].sum()
    assert contested_patches(marked[1], g.spec.res, 1.0)[1] == []


def test_only_ground_classes_colour_the_texture():
    """A wall, a trailer or a bus the segmenter calls "building" casts its side along its rays onto the road behind
    it: with the ground channels given, its pixels leave the colour bake (unlabelled ones stay)."""
    from pavemap.mesh.bake import Hits, bake_exposed

    surface = HeightField(0.0, 0.0, 1.0, torch.zeros(2, 2, dtype=torch.float64), torch.ones(2, 2, dtype=torch.bool))
    vid = torch.tensor([[0, 1, 2]] * 3)
    w = torch.tensor([[1.0, 0.0, 0.0]] * 3)
    c8 = torch.tensor([[100, 100, 100], [250, 0, 0], [120, 120, 120]], dtype=torch.uint8)  # road, building, unknown
    hits = [Hits(vid, w, c8, torch.zeros(3, dtype=torch.long), torch.tensor([0, 1, -1]))]
    ground = torch.tensor([True, False])
    rgb_all = bake_exposed(surface, None, None, 1.0, hits=hits)[0]
    rgb_ground = bake_exposed(surface, None, None, 1.0, hits=hits, ground=ground)[0]
    assert rgb_all[0, 0, 0] == pytest.approx((100 + 250 + 120) / 3 / 255, abs=1e-3)
    assert rgb_ground[0, 0].tolist() == pytest.approx([110 / 255] * 3, abs=1e-3)
