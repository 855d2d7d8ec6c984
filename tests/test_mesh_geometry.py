"""Stage 1 without depth (issue 12): the geometry from triangulated ground points, the camera-height prior,
the run's self-check and the observed layer."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import torch

from pavemap.geometry.grid import GridSpec
from pavemap.geometry.triangulate import sample_grid
from pavemap.io.sequence import read_sequence
from pavemap.mesh import MeshConfig, reconstruct
from pavemap.mesh.geometry import find_geometry, self_check
from pavemap.mesh.setup import prepare


@pytest.fixture(scope="module")
def drive(tmp_path_factory):
    """A small no-depth front-camera drive (12 frames at 10 Hz, half resolution), its true surface and the
    true height of the camera above it."""
    from pavemap.synth import synthesize

    root = tmp_path_factory.mktemp("geom") / "kitti"
    synthesize(root, "kitti-like", seed=5, frames=12, scale=0.5, depth="none", progress=False)
    seq = read_sequence(root)
    grid = GridSpec.from_dict(json.loads((root / "truth" / "height.json").read_text()))
    heights = np.load(root / "truth" / "height.npy").astype(np.float64)
    C = np.array([f.views["CAM_FRONT"].T_world_cam[:3, 3] for f in seq.frames])
    cam_true = float(np.median(C[:, 2] - sample_grid(grid, heights, C[:, :2])))
    return seq, grid, heights, cam_true


def _cfg(**kw) -> MeshConfig:
    return MeshConfig(crop_m=5.0, pe_levels=4, epochs=1, render_scale=0.25, eval_scale=0.25, resume=False,
                      pixels_per_step=32768, **kw)


@pytest.fixture(scope="module")
def run(drive, tmp_path_factory):
    out = tmp_path_factory.mktemp("geom_run")
    with pytest.warns(UserWarning):
        mesh, metrics = reconstruct(drive[0], out, _cfg(), progress=False)
    return mesh, metrics, out


def test_no_depth_drive_reconstructs_without_bias(drive, run):
    _, grid, heights, cam_true = drive
    mesh, metrics, out = run
    geo = metrics["geometry"]
    assert geo["source"] == "ground points" and geo["trustworthy"], geo["warnings"]
    assert abs(geo["camera_height"]["found_m"] - cam_true) <= 0.02
    s = mesh.surface
    obs = (s.valid & mesh.observed).numpy()
    assert 0.2 <= obs.sum() / s.valid.sum().item() <= 1.0  # a 12-frame drive: most of the crop is unseen
    xy = s.grid_xy()[torch.from_numpy(obs)].double().numpy()
    err = s.heights.numpy()[obs] - sample_grid(grid, heights, xy)
    assert abs(np.nanmean(err)) <= 0.02
    # the observed layer travels with the mesh: a PLY vertex property and a BEV raster
    assert b"property uchar observed" in (out / "mesh.ply").read_bytes()[:1000]
    assert np.array_equal(np.load(out / "bev_observed.npy"), obs)
    saved = json.loads((out / "metrics.json").read_text())
    # the check is independent evidence: held-out points the surface (relief, depth loss, anchoring) never saw
    assert saved["geometry"]["check"]["held_out"] and saved["geometry"]["check"]["points"] >= 40


def test_a_wrong_camera_height_prior_is_corrected(drive):
    seq, _, _, cam_true = drive
    notes: list[str] = []
    cfg = _cfg(camera_height=cam_true + 0.5)
    data = prepare(seq, cfg, torch.device("cpu"), notes.append)
    geo = find_geometry(seq, data, cfg, notes.append)
    assert geo.source == "ground points"
    assert abs(geo.cam_h - cam_true) <= 0.02
    # the disagreement with the prior is a warning naming both heights
    warn = [n for n in notes if n.startswith("camera height found")]
    assert warn and f"{cam_true + 0.5:.2f} m" in warn[0] and f"{geo.found:.2f} m" in warn[0]


def test_a_shifted_surface_is_flagged(drive):
    seq, grid, heights, _ = drive
    cfg = _cfg()
    notes: list[str] = []
    data = prepare(seq, cfg, torch.device("cpu"), notes.append)
    geo = find_geometry(seq, data, cfg, notes.append)
    valid = np.isfinite(heights)
    observed = valid.copy()
    good = self_check(geo, grid, heights, valid, observed, cfg, notes.append)
    assert good["trustworthy"] and abs(good["check"]["median_m"]) < 0.02
    bad = self_check(geo, grid, heights + 0.3, valid, observed, cfg, notes.append)
    assert not bad["trustworthy"] and bad["check"]["flagged"]
    assert any(w.startswith("surface not trustworthy") and "0.30 m" in w for w in bad["warnings"])
    # a surface nobody observed is not trusted either
    blind = self_check(geo, grid, heights, valid, np.zeros_like(valid), cfg, notes.append)
    assert blind["observed_fraction"] == 0 and blind["warnings"][0].startswith("mesh mostly unobserved")


def test_a_single_frame_is_not_a_confident_map(drive):
    seq = dataclasses.replace(drive[0], frames=drive[0].frames[:1])
    with pytest.warns(UserWarning, match="geometry not observable"):
        _, metrics = reconstruct(seq, None, dataclasses.replace(_cfg(), crop_m=12.0), progress=False)
    geo = metrics["geometry"]
    assert not geo["observable"] and not geo["trustworthy"]
    assert any(w.startswith("geometry not observable") for w in metrics["warnings"])


def test_poses_with_a_wrong_scale_are_named(drive):
    """Poses x2 (a wrong unit, an SfM scale): the ground the images show lies twice as far below the
    cameras as the mount height says. The ground-point sweep (prior x0.6 .. x1.65) reaches it only where the
    road's grade brings it into range, and those points say 2.3 m; the search centred on that finds the road
    at twice the mount height, and the warning names the scale."""
    seq = dataclasses.replace(drive[0], frames=[dataclasses.replace(f) for f in drive[0].frames])
    for f in seq.frames:
        f.views = {k: dataclasses.replace(v, T_world_cam=np.r_[np.c_[v.T_world_cam[:3, :3],
                                                                   2.0 * v.T_world_cam[:3, 3]], [[0, 0, 0, 1]]])
                   for k, v in f.views.items()}
    cfg = _cfg(camera_height=drive[3])
    notes: list[str] = []
    data = prepare(seq, cfg, torch.device("cpu"), notes.append)
    geo = find_geometry(seq, data, cfg, notes.append)
    assert geo.source == "ground points" and data.gp.stats["recentred_from_m"] == pytest.approx(drive[3], abs=1e-3)
    assert abs(geo.found / (2 * drive[3]) - 1) < 0.03, geo.found
    warn = [n for n in notes if "wrong scale" in n]
    assert warn and f"(x{geo.found / cfg.camera_height:.2f})" in warn[0], notes


def test_ground_points_hand_their_images_to_the_pool(drive, monkeypatch):
    """Without depth, every training image is decoded once: the ground points read it and the pool takes it
    from them, pixel for pixel what the pool decodes on its own."""
    import pavemap.mesh.data as data_mod
    import pavemap.mesh.ground_points as gp_mod
    from pavemap.io.sequence import load_rgb

    seq = drive[0]
    calls: list[str] = []

    def counted(path):
        calls.append(str(path))
        return load_rgb(path)

    monkeypatch.setattr(data_mod, "load_rgb", counted)
    monkeypatch.setattr(gp_mod, "load_rgb", counted)
    cfg = _cfg()
    notes: list[str] = []
    shared = prepare(seq, cfg, torch.device("cpu"), notes.append)
    assert shared.gp is not None and shared.gp.observable
    assert len(calls) == len(set(calls)) == len(seq.frames)  # training and held-out views, once each
    own = prepare(seq, dataclasses.replace(cfg, ground_points="off"), torch.device("cpu"), notes.append)
    assert own.gp is None
    assert torch.equal(shared.pool.rgb, own.pool.rgb) and torch.equal(shared.pool.uv, own.pool.uv)


def test_defects_say_whether_they_lie_where_the_texture_may_hold_a_vehicle():
    """mark_observed sets each defect's ``observed`` and ``texture_contested`` from the mesh's layers (the
    GIS and CSV property of that name), and leaves a layer the mesh lacks unset."""
    import torch
    from shapely.geometry import box

    from pavemap.geometry import HeightField
    from pavemap.mesh.geometry import mark_observed
    from pavemap.mesh.model import RoadMesh
    from pavemap.types import DefectInstance

    ny, nx = 40, 60
    valid = torch.ones(ny, nx, dtype=torch.bool)
    contested = torch.zeros(ny, nx, dtype=torch.bool)
    contested[10:20, 30:50] = True  # x 3.0-4.9 m, y 1.0-1.9 m
    surf = HeightField(0.0, 0.0, 0.1, torch.zeros(ny, nx), valid)
    mesh = RoadMesh(surf, torch.zeros(ny * nx, 3), torch.zeros(ny * nx, 1), [0], False, valid.clone(), None,
                    contested)

    def inst(i: int, x: float, y: float) -> DefectInstance:
        return DefectInstance(id=i, cls=3, polygon=box(x - 0.1, y - 0.1, x + 0.1, y + 0.1), severity_mean=0.5,
                              severity_max=0.5, confidence=0.5, observations=2, probability=0.9, area_m2=0.04,
                              length_m=0.2, centroid=(x, y), priority="monitor")

    on, off, outside = inst(1, 4.0, 1.5), inst(2, 1.0, 3.0), inst(3, 50.0, 1.5)
    mark_observed([on, off, outside], mesh)
    assert on.extra == {"observed": True, "texture_contested": True}
    assert off.extra == {"observed": True, "texture_contested": False}
    assert outside.extra == {"observed": False, "texture_contested": False}  # off the grid: neither
    unchecked = inst(4, 4.0, 1.5)
    mark_observed([unchecked], RoadMesh(surf, mesh.rgb, mesh.sem_logits, [0], False, None, None, None))
    assert unchecked.extra == {}
