"""Stage-1 renderer: exact against the brute-force rasterizer, gradients reach heights and attributes."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from pavemap.geometry import pixel_grid, pixel_rays, surface_bounds
from pavemap.geometry.reference import reference_intersect
from pavemap.mesh import RoadMesh, render_view
from pavemap.mesh.model import RoadMeshModel, build_grid
from pavemap.mesh.render import view_rays
from pavemap.mesh.step import forward_rays
from pavemap.types import Camera, SemanticClass
from test_geometry import _look_at, curb_field


def _mesh(seed: int = 0) -> RoadMesh:
    hf = curb_field(seed, dtype=torch.float32)
    g = torch.Generator().manual_seed(seed)
    rgb = torch.rand(hf.ny, hf.nx, 3, generator=g)
    sem = torch.randn(hf.ny, hf.nx, 3, generator=g)
    return RoadMesh(hf, rgb, sem, [0, 2, 9])


def test_render_view_matches_bruteforce():
    mesh = _mesh()
    cam = Camera("c", 80, 60, np.array([[50.0, 0, 39.5], [0, 50.0, 29.5], [0, 0, 1]]))
    T = _look_at([1.0, -1.5, 1.6], [3.0, 2.5, 0.0])
    out = render_view(mesh, cam, T, scale=0.5)
    H, W = 30, 40
    assert out["rgb"].shape == (H, W, 3) and out["sem_logits"].shape == (H, W, 3)
    assert out["labels"].shape == (H, W) and out["depth"].shape == (H, W) and out["valid"].dtype == torch.bool
    # reference on the same (scaled) pixels, in float64
    cs = cam.scaled(0.5)
    o, d = pixel_rays(cs.K, T, pixel_grid(W, H, dtype=torch.float64))
    lam_r, hit_r, ids_r, bary_r = reference_intersect(mesh.surface, o.numpy(), d.numpy())
    valid = out["valid"].reshape(-1).numpy()
    assert hit_r.mean() > 0.4
    agree = valid == hit_r
    assert agree.mean() >= 0.995
    both = valid & hit_r
    rgb_r = (bary_r[:, :, None] * mesh.dense(mesh.rgb).reshape(-1, 3).double().numpy()[ids_r]).sum(1)
    sem_r = (bary_r[:, :, None] * mesh.dense(mesh.sem_logits).reshape(-1, 3).double().numpy()[ids_r]).sum(1)
    close = np.abs(out["rgb"].reshape(-1, 3).numpy() - rgb_r).max(1) < 1e-3
    assert close[both].mean() >= 0.995  # same triangle and weights: equal colours
    assert np.abs(out["sem_logits"].reshape(-1, 3).numpy() - sem_r)[both & close].max() < 1e-3
    assert np.abs(out["depth"].reshape(-1).numpy() - np.where(hit_r, lam_r, 0))[both & close].max() < 1e-3
    labels = out["labels"].reshape(-1).numpy()
    assert set(np.unique(labels[valid])) <= {0, 2, 9} and (labels[~valid] == -1).all()
    assert (out["depth"].reshape(-1).numpy()[~valid] == 0).all()


def test_view_rays_equal_pixel_rays():
    K = np.array([[50.0, 0, 39.5], [0, 52.0, 29.5], [0, 0, 1]])
    Ts = [_look_at([0, 0, 1.5], [5, 1, 0]), _look_at([2, 1, 1.4], [-3, 2, 0])]
    px = pixel_grid(8, 6)
    view = torch.tensor([0] * 48 + [1] * 48)
    uv = torch.cat([px, px])
    Ks = torch.tensor(K, dtype=torch.float32)[None].expand(2, 3, 3)
    o, d = view_rays(Ks, torch.tensor(np.array(Ts), dtype=torch.float32), view, uv)
    for k, T in enumerate(Ts):
        o2, d2 = pixel_rays(K, T, px)
        assert torch.allclose(o[48 * k:48 * (k + 1)], o2, atol=1e-5)
        assert torch.allclose(d[48 * k:48 * (k + 1)], d2, atol=1e-5)


def test_gradients_reach_mlp_colours_logits_and_poses():
    grid = build_grid(np.array([[0.0, 0.0], [3.0, 0.0]]), 0.1, 2.0)
    model = RoadMeshModel(grid, 4, levels=4, hidden=32, z_base=0.0, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        model.height_mlp.mlp1[-1].bias.fill_(0.01)  # make the last layer's inputs matter
    cache = model.dense(model.heights().detach(), fill=0.0).reshape(-1)
    bounds = surface_bounds(model.field(cache), torch.float32)
    T = torch.tensor(_look_at([0.5, -0.5, 1.5], [2.5, 0.5, 0.0]), dtype=torch.float32, requires_grad=True)
    K = np.array([[20.0, 0, 9.5], [0, 20.0, 7.5], [0, 0, 1]])
    o, d = pixel_rays(K, T, pixel_grid(20, 16))
    fw = forward_rays(model, cache, bounds, o, d, 50.0)
    assert fw is not None
    rows, tri, bary, lam, rgb, sem, ht = fw
    assert rows.numel() > 100 and torch.allclose(bary.sum(1), torch.ones(rows.numel()), atol=1e-5)
    loss = (rgb - 0.5).abs().mean() + torch.nn.functional.cross_entropy(sem, torch.zeros_like(rows)) \
        + lam.mean() + ((ht - ht.roll(1, 1)) ** 2).mean()
    loss.backward()
    assert model.rgb.grad is not None and model.rgb.grad.is_sparse
    assert model.sem.grad is not None and model.sem.grad.coalesce().values().abs().sum() > 0
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in model.height_mlp.parameters())
    assert T.grad is not None and T.grad.abs().sum() > 0


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_render_cuda_equals_cpu():
    mesh = _mesh(1)
    cam = Camera("c", 40, 30, np.array([[25.0, 0, 19.5], [0, 25.0, 14.5], [0, 0, 1]]))
    T = _look_at([1.0, -1.5, 1.6], [3.0, 2.5, 0.0])
    a = render_view(mesh, cam, T)
    surf = mesh.surface.to("cuda")
    mc = RoadMesh(surf, mesh.rgb.cuda(), mesh.sem_logits.cuda(), mesh.class_ids)
    b = render_view(mc, cam, T)
    assert (a["valid"] == b["valid"].cpu()).float().mean() > 0.995
    both = a["valid"] & b["valid"].cpu()
    assert torch.allclose(a["rgb"][both], b["rgb"].cpu()[both], atol=1e-3)


def test_road_mask_and_labels():
    mesh = _mesh()
    classes = [SemanticClass(0, "road", road=True), SemanticClass(2, "curb"), SemanticClass(9, "x", road=True)]
    m = mesh.road_mask(classes)
    lab = mesh.labels()
    assert torch.equal(m, ((lab == 0) | (lab == 9)) & mesh.surface.valid)
    mesh.has_semantics = False
    assert torch.equal(mesh.road_mask(classes), mesh.surface.valid)


def test_road_mesh_keeps_attributes_per_vertex():
    """A RoadMesh stores colours and logits per kept vertex (a long drive's grid box is ~10x its road): dense
    arrays given are taken to the kept vertices, per-vertex lookups of other cells say -1, hits interpolate as
    the dense arrays would, and a wrong shape is refused naming the field."""
    hf = curb_field(1, dtype=torch.float32)
    valid = hf.valid.clone()
    valid[:, :3] = False
    from pavemap.geometry import HeightField, intersect_rays

    surf = HeightField(hf.x0, hf.y0, hf.res, hf.heights, valid)
    g = torch.Generator().manual_seed(2)
    rgb, sem = torch.rand(hf.ny, hf.nx, 3, generator=g), torch.randn(hf.ny, hf.nx, 4, generator=g)
    mesh = RoadMesh(surf, rgb, sem, [0, 1, 2, 3])
    n = int(valid.sum())
    assert mesh.rgb.shape == (n, 3) and mesh.sem_logits.shape == (n, 4)
    assert torch.equal(mesh.dense(mesh.rgb)[valid], rgb[valid]) and not mesh.dense(mesh.rgb)[~valid].any()
    flat = torch.arange(hf.nx * hf.ny)
    k = mesh.vertex_of(flat)
    assert torch.equal(k >= 0, valid.reshape(-1)) and torch.equal(k[k >= 0], torch.arange(n))
    cam = Camera("c", 60, 40, np.array([[40.0, 0, 29.5], [0, 40.0, 19.5], [0, 0, 1]]))
    o, d = pixel_rays(cam.K, _look_at([1.0, -1.5, 1.6], [3.0, 2.5, 0.0]), pixel_grid(60, 40))
    hit = intersect_rays(surf, o, d)
    assert hit.hit.any()
    assert torch.allclose(mesh.at_hits(hit, mesh.sem_logits), hit.interpolate(sem), atol=1e-6)
    assert torch.equal(mesh.labels()[~valid], torch.full((int((~valid).sum()),), -1))
    with pytest.raises(ValueError, match="RoadMesh.rgb"):
        RoadMesh(surf, torch.rand(n + 1, 3), mesh.sem_logits, [0, 1, 2, 3])
