"""A camera scaled to a rounded image size: its K must describe the resized image the pool holds (issue 47: an
800 x 450 image at 0.25 is 200 x 112, rows 0.2489 of the full ones; with K scaled by 0.25 the bottom rows sat
0.5 px off, which lifted the multi-view consistency of the nuScenes-like drive by 1.2 cm)."""

from __future__ import annotations

import numpy as np
import pytest

from pavemap.mesh.data import _depth_samples, _resize
from pavemap.types import Camera


def _ramp(h: int, w: int) -> np.ndarray:
    """(h, w) float32 image whose value is the full-resolution pixel centre's coordinate: row (axis 0 ramp)
    in the first, column in the second."""
    v, u = np.meshgrid(np.arange(h, dtype=np.float32), np.arange(w, dtype=np.float32), indexing="ij")
    return np.stack([v, u])


@pytest.mark.parametrize(("w", "h", "scale"), [(800, 450, 0.25), (1241, 376, 0.25), (640, 301, 0.5)])
def test_scaled_k_maps_full_pixels_onto_the_resized_image(w, h, scale):
    cam = Camera("c", w, h, np.array([[500.0, 0.0, w / 2 - 3.2], [0.0, 500.0, h / 2 + 1.7], [0.0, 0.0, 1.0]]))
    small = cam.scaled(scale)
    rows, cols = (_resize(a, (small.width, small.height), nearest=False) for a in _ramp(h, w))
    assert rows.shape == (small.height, small.width)
    # each small pixel's centre, taken back to the full image through K_small^-1 then K, must be the full-image
    # position the resized ramp holds there (the area average of a ramp is its value at the box's centre). PIL's
    # box filter missed it by up to +-0.5 source px at a ratio that is not whole (whole source pixels per box).
    A = cam.K @ np.linalg.inv(small.K)
    vs, us = np.meshgrid(np.arange(small.height), np.arange(small.width), indexing="ij")
    full = np.einsum("ij,hwj->hwi", A, np.stack([us, vs, np.ones_like(us)], -1).astype(np.float64))
    err_v, err_u = np.abs(rows - full[..., 1]), np.abs(cols - full[..., 0])
    assert err_v.max() < 0.02 and err_u.max() < 0.02, (float(err_v.max()), float(err_u.max()))


def test_depth_samples_sit_where_the_scaled_k_puts_them():
    cam = Camera("c", 800, 450, np.array([[600.0, 0.0, 400.0], [0.0, 600.0, 230.0], [0.0, 0.0, 1.0]]))
    small = cam.scaled(0.25)
    dep = np.zeros((450, 800), np.float32)
    dep[440, 100] = 7.0
    out, uv = _depth_samples(dep, (small.width, small.height), 0.25)
    j, i = np.argwhere(out > 0)[0]
    want = (small.K @ np.linalg.inv(cam.K) @ np.array([100.0, 440.0, 1.0]))[:2]
    assert np.allclose(uv[j, i], want, atol=1e-4), (uv[j, i], want)
