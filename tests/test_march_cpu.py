"""The compiled CPU march (pavemap.geometry.march_cpu) against the torch reference march it replaces on a CPU."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from pavemap.geometry import find_hits, intersect_rays, march_cpu, surface_bounds
from pavemap.geometry.heightfield import HeightField, _find_roots
from test_geometry import curb_field

pytestmark = pytest.mark.skipif(not march_cpu.available(), reason="numba not installed")


def _road(seed: int = 0) -> HeightField:
    """A 40 x 30 m drive-sized field: grade, crown, a 15 cm kerb, noise, holes in the crop (tile skipping and
    missing triangles both matter)."""
    rng = np.random.default_rng(seed)
    ny, nx = 300, 400
    y, x = np.meshgrid(np.arange(ny) * 0.1, np.arange(nx) * 0.1, indexing="ij")
    h = 0.02 * x + 0.04 * np.cos(y / 4.0) + 0.01 * rng.standard_normal((ny, nx))
    h[y > 24] += 0.15
    valid = np.ones((ny, nx), bool)
    valid[:, :15] = False
    valid[120:140, 200:260] = False
    return HeightField(-5.0, 3.0, 0.1, torch.tensor(h, dtype=torch.float32), torch.tensor(valid))


def _rays(hf: HeightField, n: int, seed: int, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
    """Camera-like rays: 1.2-2.8 m above the grid, looking down at 0.5-60 degrees, some upward or level."""
    g = torch.Generator().manual_seed(seed)
    x0, x1, y0, y1 = hf.extent
    o = torch.stack([x0 + (x1 - x0) * torch.rand(n, generator=g), y0 + (y1 - y0) * torch.rand(n, generator=g),
                     1.2 + 1.6 * torch.rand(n, generator=g)], 1)
    az = 2 * torch.pi * torch.rand(n, generator=g)
    el = torch.deg2rad(-60 + 62 * torch.rand(n, generator=g))  # a few level or upward rays: misses
    d = torch.stack([torch.cos(el) * torch.cos(az), torch.cos(el) * torch.sin(az), torch.sin(el)], 1)
    return o.to(dtype), d.to(dtype)


def _as_dict(res) -> dict[int, tuple]:
    idx, lam, i, j, lower = res
    return {int(k): (float(lam[n]), int(i[n]), int(j[n]), bool(lower[n])) for n, k in enumerate(idx.tolist())}


@pytest.mark.parametrize("seed", [0, 1])
def test_compiled_march_equals_the_torch_march_in_float64(seed):
    hf = _road(seed)
    o, d = _rays(hf, 20000, seed, torch.float64)
    b = surface_bounds(hf, torch.float64)
    ref = _as_dict(_find_roots(hf, o, d, 200.0, 0.5, 16, 40, b))
    new = _as_dict(march_cpu.find_roots_cpu(hf, o, d, 200.0, 0.5, 16, 40, b))
    assert len(ref) > 5000 and set(ref) == set(new)  # the same rays hit ...
    assert all(ref[k][1:] == new[k][1:] for k in ref)  # ... the same triangles ...
    assert max(abs(ref[k][0] - new[k][0]) for k in ref) < 1e-9  # ... at the same depth


def test_compiled_march_agrees_with_the_torch_march_in_float32():
    """float32 rays: the kernel computes in float64, so rounding may move a grazing ray to a neighbouring
    triangle or across a crop edge, but almost never."""
    hf = _road(2)
    o, d = _rays(hf, 20000, 2, torch.float32)
    b = surface_bounds(hf, torch.float32)
    ref = _as_dict(_find_roots(hf, o, d, 200.0, 0.5, 16, 40, b))
    new = _as_dict(march_cpu.find_roots_cpu(hf, o, d, 200.0, 0.5, 16, 40, b))
    both = set(ref) & set(new)
    assert len(set(ref) ^ set(new)) <= 0.002 * len(ref)
    same = [k for k in both if ref[k][1:] == new[k][1:]]
    assert len(same) >= 0.998 * len(both)
    assert np.median([abs(ref[k][0] - new[k][0]) for k in same]) < 1e-5
    assert new[same[0]][0] == pytest.approx(ref[same[0]][0], abs=1e-3)


def test_find_hits_uses_the_kernel_on_a_cpu_unless_told_not_to(monkeypatch):
    hf = curb_field(3)
    o = torch.tensor([[0.5, 0.5, 1.6], [2.0, 1.0, 1.5]], dtype=torch.float64)
    d = torch.nn.functional.normalize(torch.tensor([[0.6, 0.5, -0.4], [0.0, 0.2, 1.0]], dtype=torch.float64), dim=1)
    calls = []
    real = march_cpu.find_roots_cpu
    monkeypatch.setattr(march_cpu, "find_roots_cpu", lambda *a: calls.append(1) or real(*a))
    cells = find_hits(hf, o, d)
    assert calls and cells.idx.tolist() == [0]  # the second ray points up: a miss
    monkeypatch.setenv("PAVEMAP_MARCH", "torch")
    assert not march_cpu.use_for(o)
    ref = find_hits(hf, o, d)
    assert len(calls) == 1 and torch.equal(ref.idx, cells.idx) and torch.allclose(ref.lam0, cells.lam0)
    # the differentiable half is shared: the hit lies on the ray at the root both found
    monkeypatch.delenv("PAVEMAP_MARCH")
    hit = intersect_rays(hf, o, d)
    assert hit.hit.tolist() == [True, False]
    assert torch.allclose(hit.points[0], o[0] + ref.lam0[0] * d[0], atol=1e-9)
    z, _ = hf.height_at(hit.points[:1, :2])
    assert float(z[0]) == pytest.approx(float(hit.points[0, 2]), abs=1e-9)


def test_without_numba_the_torch_march_runs(monkeypatch):
    """A missing or broken numba (available() False) is not an error: find_hits marches with torch."""
    hf = curb_field(4)
    o = torch.tensor([[0.5, 0.5, 1.6]], dtype=torch.float64)
    d = torch.nn.functional.normalize(torch.tensor([[0.6, 0.5, -0.4]], dtype=torch.float64), dim=1)
    monkeypatch.setattr(march_cpu, "available", lambda: False)
    monkeypatch.setattr(march_cpu, "find_roots_cpu", lambda *a: pytest.fail("the compiled march ran"))
    assert not march_cpu.use_for(o)
    assert find_hits(hf, o, d).idx.tolist() == [0]
