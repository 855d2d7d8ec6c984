"""Per-view exposure (pavemap.mesh.exposure): the fit, the gauge, interpolation and the exposed bake."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from mesh_scene import read_scene, texture
from pavemap.mesh import exposure
from pavemap.mesh.bake import bake_colours, bake_exposed
from pavemap.mesh.data import ViewKey
from test_mesh_bake import _all_views_pool, _field, _true_surface


def test_fit_recovers_gains_up_to_the_gauge():
    g = torch.Generator().manual_seed(0)
    n_views, per = 5, 4000
    gains = torch.tensor([1.0, 0.7, 1.3, 0.9, 1.1], dtype=torch.float64)
    offsets = torch.tensor([0.0, 0.05, -0.04, 0.02, 0.0], dtype=torch.float64)
    view = torch.arange(n_views).repeat_interleave(per)
    pred = torch.rand(n_views * per, 3, generator=g, dtype=torch.float64) * 0.6 + 0.2
    obs = gains[view, None] * pred + offsets[view, None] + 0.01 * torch.randn(pred.shape, generator=g,
                                                                              dtype=torch.float64)
    e = exposure.fit(view, pred, obs, n_views)
    # the gauge: mean gain 1 and mean offset 0 over the views (equal pixel counts here)
    assert abs(float(e[:, 0].mean()) - 1.0) < 1e-9 and abs(float(e[:, 1].mean())) < 1e-9
    # ratios of gains are gauge-free: recovered to 2 %
    ratio_true = gains / gains[0]
    ratio = e[:, 0] / e[0, 0]
    assert torch.allclose(ratio, ratio_true, rtol=0.02), (ratio, ratio_true)
    # applying then compensating is the identity
    c = torch.rand(10, 3, dtype=torch.float64)
    v = torch.arange(10) % n_views
    assert torch.allclose(exposure.compensate(exposure.apply(c, e, v), e, v), c)


def test_a_view_without_pixels_keeps_the_prior_and_a_wild_fit_is_refused():
    view = torch.zeros(3000, dtype=torch.long)
    pred = torch.rand(3000, 3, dtype=torch.float64)
    e = exposure.fit(view, pred, 50.0 * pred, 2)  # view 0: gain 50 is no exposure; view 1: no pixels
    assert torch.allclose(e, exposure.identity(2))
    # nor is an offset of 0.7 (of a colour range of 1) with a plausible gain
    e = exposure.fit(view, pred, 0.9 * pred - 0.7, 2)
    assert torch.allclose(e, exposure.identity(2))


def test_interpolation_per_camera_in_time():
    train = [ViewKey(0, "a"), ViewKey(10, "a"), ViewKey(0, "b")]
    e = torch.tensor([[1.0, 0.0], [2.0, 0.1], [0.5, 0.2]], dtype=torch.float64)
    out = exposure.interpolate(train, e, [ViewKey(5, "a"), ViewKey(20, "a"), ViewKey(7, "b"), ViewKey(3, "c")])
    assert torch.allclose(out, torch.tensor([[1.5, 0.05], [2.0, 0.1], [0.5, 0.2], [1.0, 0.0]],
                                            dtype=torch.float64))


@pytest.fixture(scope="module")
def seq(tmp_path_factory):
    return read_scene(tmp_path_factory.mktemp("exposure") / "seq", frames=6, width=64, height=40)


def test_exposed_bake_undoes_per_view_exposure(seq):
    g, xy, heights = _true_surface(seq)
    pool = _all_views_pool(seq)
    # darken and brighten alternate views, as an auto-exposure camera driving through shade would
    gains = torch.tensor([0.7 if i % 2 else 1.1 for i in range(len(pool.keys))])
    rgb = (pool.rgb.float() * gains[pool.view, None]).clamp(0, 255).round().to(torch.uint8)
    exposed = dataclasses.replace(pool, rgb=rgb)
    surf = _field(g, heights)
    tex = torch.from_numpy(texture(xy).reshape(*g.spec.shape, 3)).float()
    plain, support, _ = bake_colours(surf, exposed, exposed.T, 60.0)
    fitted, _, _, e = bake_exposed(surf, exposed, exposed.T, 60.0, exposure_rounds=3)
    seen = (support > 2.0) & torch.from_numpy(g.valid.copy())

    def err(rgb_: torch.Tensor) -> float:
        # the texture is recovered up to the gauge: compare after the best global gain
        a, b = rgb_[seen].reshape(-1).double(), tex[seen].reshape(-1).double()
        return float(((a * (a @ b) / (a @ a) - b).abs()).median())

    assert e is not None and e.shape == (len(pool.keys), 2)
    # dark over bright views: 0.636; the prior (1, 0) holds back views of ~1,700 pixels by ~10 %
    ratio = float(e[1::2, 0].median() / e[0::2, 0].median())
    assert 0.6 < ratio < 0.75, ratio
    assert err(fitted) < 0.5 * err(plain), (err(fitted), err(plain))
    assert np.isfinite(err(fitted))


def test_exposed_bake_of_a_surface_no_pixel_reaches(seq):
    g, _, heights = _true_surface(seq)
    pool = _all_views_pool(seq)
    far = _field(g, heights - 100.0)  # 100 m below every ray's reach
    rgb, support, coloured, e = bake_exposed(far, pool, pool.T, 60.0, exposure_rounds=2)
    assert e is None and float(support.sum()) == 0.0 and not coloured.any()
