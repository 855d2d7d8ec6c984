"""pavemap.geometry: rays, projection and exact height-field ray casting vs a brute-force rasterizer."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from pavemap.geometry import HeightField, intersect_rays, pixel_grid, pixel_rays, project
from pavemap.geometry.reference import reference_intersect


def _look_at(eye, target, up=(0, 0, 1)) -> np.ndarray:
    """Camera-to-world pose (OpenCV axes) at ``eye`` looking at ``target``."""
    eye, target, up = (np.asarray(a, dtype=np.float64) for a in (eye, target, up))
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z], 1)
    T[:3, 3] = eye
    return T


def curb_field(seed: int = 0, nx: int = 26, ny: int = 22, res: float = 0.25, dtype=torch.float64) -> HeightField:
    """Random rough road with a raised curb + sidewalk strip and a cropped-out corner."""
    rng = np.random.default_rng(seed)
    h = 0.03 * rng.standard_normal((ny, nx))
    xs = np.arange(nx) * res
    h += 0.05 * np.sin(xs / 1.3)[None, :]
    h[:, int(nx * 0.7):] += 0.15  # curb: a 15 cm step over one cell
    h[int(ny * 0.3):int(ny * 0.3) + 2, 3:8] -= 0.12  # a pothole
    valid = np.ones((ny, nx), dtype=bool)
    valid[:4, :5] = False
    valid[-3:, -6:] = False
    return HeightField(-1.0, -2.0, res, torch.tensor(h, dtype=dtype), torch.tensor(valid))


def _camera(width=64, height=48):
    K = np.array([[40.0, 0, (width - 1) / 2], [0, 40.0, (height - 1) / 2], [0, 0, 1]])
    return K


def test_pixel_rays_project_roundtrip():
    K = _camera()
    T = _look_at([0.3, -0.5, 1.6], [2.0, 3.0, 0.0])
    px = pixel_grid(64, 48, dtype=torch.float64)
    o, d = pixel_rays(K, T, px)
    lam = torch.linspace(0.5, 9.0, px.shape[0], dtype=torch.float64)
    pts = o + lam[:, None] * d
    uv, depth = project(K, T, pts)
    assert torch.allclose(uv, px, atol=1e-8)
    assert torch.allclose(depth, lam, atol=1e-10)  # lam is camera depth
    assert torch.allclose(o[0], torch.tensor(T[:3, 3]))


def test_height_at_and_plane():
    hf = HeightField.plane(0.0, 0.0, 0.5, 5, 4, z=1.25)
    z, inside = hf.height_at(torch.tensor([[0.3, 0.7], [2.0, 1.5], [2.1, 0.1], [-0.01, 1.0]]))
    assert inside.tolist() == [True, True, False, False]
    assert torch.allclose(z[:2], torch.tensor([1.25, 1.25]))
    assert hf.vertices().shape == (20, 3)
    assert hf.faces().shape == (2 * 4 * 3, 3)
    # Exact bilinear-free triangle interpolation: the lower/upper rule of DESIGN.
    hf2 = HeightField(0.0, 0.0, 1.0, torch.tensor([[0.0, 1.0], [2.0, 4.0]]), torch.ones(2, 2, dtype=torch.bool))
    z, _ = hf2.height_at(torch.tensor([[0.75, 0.25], [0.25, 0.75]]))
    # lower: (1-fx)*h00 + (fx-fy)*h10 + fy*h11 ; upper: (1-fy)*h00 + fx*h11 + (fy-fx)*h01
    assert torch.allclose(z, torch.tensor([0.5 * 1.0 + 0.25 * 4.0, 0.25 * 4.0 + 0.5 * 2.0]))


@pytest.mark.parametrize("legacy", [False, True])
def test_truth_height_reader(tmp_path, legacy):
    from pavemap.geometry import GridSpec
    from pavemap.io.truth import read_truth_height, write_truth_height

    a = np.arange(12, dtype=np.float32).reshape(3, 4)
    a[0, 0] = np.nan
    grid = GridSpec(1.0, 2.0, 0.5, 4, 3)
    write_truth_height(tmp_path, a, grid)
    if legacy:  # files written before GridSpec
        (tmp_path / "truth" / "height.json").write_text(
            json.dumps({"x_min": 1.0, "y_min": 2.0, "resolution": 0.5, "shape": [3, 4]}))
    hf = read_truth_height(tmp_path)
    assert (hf.nx, hf.ny, hf.res, hf.x0, hf.y0) == (4, 3, 0.5, 1.0, 2.0) and hf.grid == grid
    assert not hf.valid[0, 0] and hf.valid.sum() == 11
    assert torch.isfinite(hf.heights).all()
    (tmp_path / "truth" / "height.json").write_text(json.dumps({"x_min": 1.0}))
    with pytest.raises(ValueError, match="height.json"):
        read_truth_height(tmp_path)


def test_truth_window_and_banded_height_error(tmp_path):
    """A window of the truth is the same cells as the whole truth cut, and the mesh's height RMSE taken in
    bands of rows with the truth's window under each equals the one taken at once."""
    from pavemap.geometry import GridSpec, HeightField
    from pavemap.io.truth import read_truth_grid, read_truth_height, write_truth_height
    from pavemap.mesh.evaluate import truth_metrics
    from pavemap.mesh.model import RoadMesh

    rng = np.random.default_rng(3)
    grid = GridSpec(-10.0, -5.0, 0.05, 801, 401)  # 40 x 20 m at 5 cm
    a = rng.normal(0.0, 0.1, grid.shape).astype(np.float32)
    a[:40, :40] = np.nan
    write_truth_height(tmp_path, a, grid)
    win, g = read_truth_grid(tmp_path, (0.02, 3.0, -1.0, 2.51))
    i0, j0 = round((g.x0 - grid.x0) / grid.res), round((g.y0 - grid.y0) / grid.res)
    assert g.x0 <= 0.02 and g.x0 + (g.nx - 1) * g.res >= 3.0 and g.y0 <= -1.0 and g.y0 + (g.ny - 1) * g.res >= 2.51
    np.testing.assert_array_equal(win, a[j0:j0 + g.ny, i0:i0 + g.nx])
    assert read_truth_grid(tmp_path, (500.0, 600.0, 500.0, 600.0))[0].shape == (2, 2)  # clamped to the grid
    h = torch.from_numpy(rng.normal(0.0, 0.1, (150, 300)).astype(np.float32))
    valid = torch.ones(150, 300, dtype=torch.bool)
    valid[:, :5] = False
    mesh = RoadMesh(HeightField(-8.0, -4.0, 0.1, h, valid), torch.zeros(int(valid.sum()), 3),
                    torch.zeros(int(valid.sum()), 0), [], False)
    seen = torch.rand(150, 300, generator=torch.Generator().manual_seed(0)) < 0.5
    whole, banded = truth_metrics(mesh, tmp_path, seen, band_rows=1000), truth_metrics(mesh, tmp_path, seen, 7)
    assert whole == pytest.approx(banded, rel=1e-6) and whole["height_rmse_seen_vertices"] > 1000
    t = read_truth_height(tmp_path)
    z, inside = t.height_at(mesh.surface.grid_xy()[valid].double())
    err = h[valid].double()[inside] - z[inside]
    assert whole["height_rmse"] == pytest.approx(float(torch.sqrt((err ** 2).mean())), rel=1e-6)


def test_geometry_does_no_file_io():
    """pavemap.geometry is pure: it imports nothing from pavemap.io (nor open()s files)."""
    import ast
    import pathlib

    import pavemap.geometry

    root = pathlib.Path(pavemap.geometry.__file__).parent
    for f in sorted(root.glob("*.py")):
        tree = ast.parse(f.read_text(encoding="utf-8"))
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom):
                names = [node.module or ""]
            elif isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            else:
                names = []
            assert not any(n == "pavemap.io" or n.startswith("pavemap.io.") for n in names), (f.name, names)
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Name):
                assert node.func.id != "open", f.name


@pytest.mark.parametrize("seed", [0, 1])
def test_intersection_matches_bruteforce(seed):
    hf = curb_field(seed)
    K = _camera()
    rng = np.random.default_rng(seed)
    n_same = n_tot = 0
    for _cam in range(3):
        eye = [rng.uniform(0, 3), rng.uniform(-1.5, 0), rng.uniform(1.2, 2.0)]
        target = [rng.uniform(1, 4), rng.uniform(2, 4), 0.0]
        T = _look_at(eye, target)
        px = pixel_grid(64, 48, dtype=torch.float64)
        o, d = pixel_rays(K, T, px)
        res = intersect_rays(hf, o, d)
        lam_r, hit_r, ids_r, bary_r = reference_intersect(hf, o.numpy(), d.numpy())
        hit = res.hit.numpy()
        assert hit_r.mean() > 0.3  # the views see a good part of the surface
        same_tri = hit & hit_r & (np.sort(res.vertex_ids.numpy(), 1) == np.sort(ids_r, 1)).all(1)
        agree = same_tri | (~hit & ~hit_r)
        n_same += agree.sum()
        n_tot += agree.size
        # Equal interpolated attributes on the same triangle: lam, points and a random attribute.
        attr = torch.tensor(rng.standard_normal((hf.ny * hf.nx, 4)))
        mine = res.interpolate(attr).numpy()[same_tri]
        ref = (bary_r[:, :, None] * attr.numpy()[ids_r]).sum(1)[same_tri]
        assert np.allclose(mine, ref, atol=1e-8)
        assert np.allclose(res.lam.numpy()[same_tri], lam_r[same_tri], atol=1e-9)
        z_surf, inside = hf.height_at(res.points[res.hit, :2])
        assert inside.all() and torch.allclose(z_surf, res.points[res.hit, 2], atol=1e-9)
    assert n_same / n_tot >= 0.995, n_same / n_tot


def test_misses_upward_and_outside():
    hf = curb_field(0)
    o = torch.tensor([[1.0, 1.0, 2.0], [1.0, 1.0, 2.0], [50.0, 50.0, 2.0], [1.0, 1.0, 2.0], [0.0, 0.0, 2.0]],
                     dtype=torch.float64)
    d = torch.tensor([[0.0, 0.0, 1.0], [0.1, 0.1, -1.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]],
                     dtype=torch.float64)
    r = intersect_rays(hf, o, d)
    assert r.hit.tolist() == [False, True, False, False, True]
    # straight down onto a vertex-free spot: z equals the surface height there
    z, _ = hf.height_at(o[4:5, :2])
    assert torch.allclose(r.points[4, 2], z[0])
    assert torch.isfinite(r.lam).all() and torch.isfinite(r.points).all()
    # an empty crop: everything misses
    hf.valid[:] = False
    assert not intersect_rays(hf, o, d).hit.any()


def test_curb_occlusion_from_road():
    """A ray skimming towards a curb must stop on the curb's face, not on the road behind it."""
    res = 0.1
    h = torch.zeros(5, 40, dtype=torch.float64)
    h[:, 20:] = 0.15
    hf = HeightField(0.0, 0.0, res, h, torch.ones(5, 40, dtype=torch.bool))
    o = torch.tensor([[0.5, 0.2, 0.1]], dtype=torch.float64)
    d = torch.tensor([[1.0, 0.0, -0.01]], dtype=torch.float64)
    r = intersect_rays(hf, o, d)
    lam_r, hit_r, _, _ = reference_intersect(hf, o.numpy(), d.numpy())
    assert r.hit.item() and hit_r[0]
    assert abs(r.lam.item() - lam_r[0]) < 1e-9
    assert 1.9 < r.points[0, 0].item() < 2.0  # on the sloped cell in front of the curb top


def test_gradcheck_heights_and_attributes():
    hf0 = curb_field(3, nx=6, ny=5, res=0.5)
    hf0.valid[:] = True
    hf0.valid[0, 0] = False
    K = np.array([[4.0, 0, 2.0], [0, 4.0, 1.5], [0, 0, 1]])
    T = _look_at([0.2, -3.0, 1.5], [0.3, -1.0, 0.0])
    px = pixel_grid(5, 4, dtype=torch.float64)
    o, d = pixel_rays(K, T, px)
    base = intersect_rays(hf0, o, d)
    assert base.hit.sum() >= 8
    attr0 = torch.randn(hf0.ny * hf0.nx, 2, dtype=torch.float64)

    def f(heights, attr, origins, dirs):
        hf = HeightField(hf0.x0, hf0.y0, hf0.res, heights, hf0.valid)
        r = intersect_rays(hf, origins, dirs)
        return r.lam, r.interpolate(attr), r.points

    h = hf0.heights.clone().requires_grad_(True)
    a = attr0.clone().requires_grad_(True)
    oo = o.clone().requires_grad_(True)
    dd = d.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(f, (h, a, oo, dd), eps=1e-6, atol=1e-5)
