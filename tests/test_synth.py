"""The synthetic world: truth consistency, renderer geometry, determinism, CLI."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from pavemap.errors import PavemapError
from pavemap.geometry.grid import GridSpec
from pavemap.io.sequence import load_depth, load_semantics, read_sequence
from pavemap.synth import load_truth_defects, load_truth_height, load_world, make_world, render_view, synthesize
from pavemap.synth.params import CLASSES
from pavemap.synth.surface import bilinear_np


def _instances(seq, f, cam) -> np.ndarray:
    v = f.views[cam]
    with Image.open(seq.root / "truth" / "instances" / cam / Path(v.image).name) as im:
        return np.asarray(im).astype(np.int64) & 0x3FFF


def _project(K, T, X):
    Xc = T[:3, :3].T @ (X - T[:3, 3])
    return K[0, 0] * Xc[0] / Xc[2] + K[0, 2], K[1, 1] * Xc[1] / Xc[2] + K[1, 2], Xc[2]


def test_world_params_and_classes():
    w = make_world("kitti-like", seed=3, frames=5, clutter=0.5, road_after=30.0)
    p = w.params
    assert 7.0 <= p.width <= 12.0 and 0.10 <= p.curb_height <= 0.15
    assert [c["id"] for c in CLASSES] == list(range(8))
    assert [c["name"] for c in CLASSES if c["road"]] == ["road", "lane_marking"]
    with pytest.raises(PavemapError, match="unknown world parameter"):
        make_world("kitti-like", seed=0, no_such_knob=1)
    with pytest.raises(PavemapError, match="road width"):
        make_world("kitti-like", seed=0, lanes=4, lane_width=3.5)
    with pytest.raises(PavemapError, match="unknown preset"):
        make_world("waymo-like", seed=0)
    # defect density: default 15-40 per 100 m of road
    n = len(w.defects) / (p.road_length / 100.0)
    assert 10 <= n <= 45, n
    # cross-section: road crown above the gutter, curb step up to the sidewalk
    s0 = p.road_before + 2.0
    t = np.array([0.0, p.width / 2 - 0.05, p.width / 2 + 0.2, p.width / 2 + 1.0])
    xy = w.xy_of_st(np.full(4, s0), -t)
    z = w.height_at(xy[:, 0], xy[:, 1])
    lab = w.label_at(xy[:, 0], xy[:, 1])
    assert z[0] > z[1] + 0.02  # crown of a few cm (superelevation stays below it on a straight)
    assert 0.08 < z[3] - z[1] < 0.25  # curb 10-15 cm (+ sidewalk cross-fall)
    assert list(lab) == [1 if lab[0] == 1 else 0, lab[1], 2, 3] and lab[1] in (0, 1)


def test_potholes_are_depressions():
    w = make_world("kitti-like", seed=1, frames=5, defect_density=40, class_mix=(0, 0, 0, 1), road_after=25.0)
    assert w.defects and all(d["cls"] == 3 for d in w.defects)
    for d in w.defects[:10]:
        c = np.asarray(d["centre"])
        rim = c + np.array([np.cos(d["rot"]), np.sin(d["rot"])]) * d["ax"] * 1.6
        depth = w.height_at(rim[:1], rim[1:])[0] - w.height_at(c[:1], c[1:])[0]
        assert 0.5 * d["depth_m"] < depth < d["depth_m"] + 0.04, (depth, d["depth_m"])
        assert 0.03 <= d["depth_m"] <= 0.10


def test_truth_files(tiny_seq):
    root = tiny_seq.root
    defects = load_truth_defects(root)
    assert defects, "no defects in the tiny world"
    assert {d.cls for d in defects} <= {0, 1, 2, 3}
    assert all(d.polygon.is_valid and d.polygon.area > 0 for d in defects)
    assert all(d.properties["code"] == d.code for d in defects)
    h, grid = load_truth_height(root)
    assert h.dtype == np.float32 and h.shape == grid.shape and grid.res == 0.05
    # height.json is the one grid format (GridSpec.to_dict), nothing else spelled
    meta = json.loads((root / "truth" / "height.json").read_text())
    assert GridSpec.from_dict(meta) == grid and {"x0", "y0", "res", "nx", "ny"} <= set(meta)
    assert not {"x_min", "y_min", "resolution"} & set(meta)
    w = load_world(root)  # rebuilt from truth/world.json: the same surface
    np.testing.assert_array_equal(w.height, h)
    d = json.loads((root / "sequence.json").read_text())
    assert [c["id"] for c in d["classes"]] == list(range(8)) and d["classes"][7]["sky"]


def test_defect_centres_project_onto_their_instance(tiny_nuscenes_seq, tiny_seq):
    """Project each GT defect centre into the views where it is visible: it lands on its own instance."""
    checked = hits = 0
    for seq in (tiny_seq, tiny_nuscenes_seq):
        h, grid = load_truth_height(seq.root)
        defects = load_truth_defects(seq.root)
        for f in seq.frames:
            for cam, v in f.views.items():
                inst = _instances(seq, f, cam)
                depth = load_depth(seq.root / v.depth) if v.depth else None
                counts = np.bincount(inst.ravel(), minlength=len(defects) + 1)
                K = seq.cameras[cam].K
                for d in defects:
                    if counts[d.id + 1] < 30:  # well resolved only: a 0.2 m crack band at 40 m is sub-pixel
                        continue
                    cx, cy = d.properties["x_m"], d.properties["y_m"]
                    X = np.array([cx, cy, bilinear_np(h, grid, np.array([cx]), np.array([cy]))[0]])
                    u, vv, z = _project(K, v.T_world_cam, X)
                    iu, iv = int(round(u)), int(round(vv))
                    if z <= 0 or not (0 <= iu < inst.shape[1] and 0 <= iv < inst.shape[0]):
                        continue
                    checked += 1
                    win = inst[max(0, iv - 1): iv + 2, max(0, iu - 1): iu + 2]
                    if (win == d.id + 1).any():
                        hits += 1
                        if depth is not None and depth[iv, iu] > 0 and inst[iv, iu] == d.id + 1:
                            # half a pixel row moves the ground hit by ~ z^2 / (fy * camera height)
                            assert abs(depth[iv, iu] - z) < 0.05 + 0.02 * z + z * z / (K[1, 1] * 1.2)
    assert checked >= 5, checked
    assert hits >= 0.95 * checked, (hits, checked)


def test_render_hits_the_exact_surface():
    """Ground pixels' depths put their 3D points on the true height field (mm level)."""
    w = make_world("kitti-like", seed=2, frames=3, road_after=40.0)
    from pavemap.synth.rig import RIGS, camera_pose, rig_cameras, vehicle_poses

    cam = rig_cameras("kitti-like", 0.3)["CAM_FRONT"]
    poses, _ = vehicle_poses(w, np.random.default_rng(0))
    T = camera_pose(poses[1], RIGS["kitti-like"][0])
    r = render_view(w, cam, T)
    ground = np.isin(r.label, [0, 1, 2, 3, 4]) & (r.depth > 0) & (r.obj == 0)
    assert ground.mean() > 0.3
    v, u = np.nonzero(ground)
    rays = np.stack([u, v, np.ones_like(u)], 1).astype(float) @ np.linalg.inv(cam.K).T @ T[:3, :3].T
    P = T[:3, 3] + r.depth[v, u, None] * rays
    err = P[:, 2] - w.height_at(P[:, 0], P[:, 1])
    assert np.percentile(np.abs(err), 99) < 0.01, np.abs(err).max()
    # road straight ahead, sky at the top row
    assert r.label[-1, cam.width // 2] in (0, 1) and (r.label[0] == 7).any()
    assert r.rgb.dtype == np.uint8 and r.rgb.shape == (cam.height, cam.width, 3)


def test_layers_and_sparse_depth(tiny_nuscenes_seq):
    seq = tiny_nuscenes_seq
    assert len(seq.cameras) == 6 and len(seq.frames) == 4
    cam = seq.cameras["CAM_FRONT"]
    assert (cam.width, cam.height) == (240, 135)
    f = seq.frames[1]
    sem = load_semantics(seq.root / f.views["CAM_FRONT"].semantics)
    assert set(np.unique(sem)) <= set(range(8)) and (sem == 0).any() and (sem == 7).any()
    fracs = [(load_depth(seq.root / v.depth) > 0).mean() for v in f.views.values()]
    assert 0.01 < np.mean(fracs) < 0.08, fracs
    # camera heights about 1.5 m above the road, pointing roughly horizontally
    T = f.views["CAM_FRONT"].T_world_cam
    h, grid = load_truth_height(seq.root)
    assert 1.3 < T[2, 3] - bilinear_np(h, grid, T[:1, 3], T[1:2, 3])[0] < 1.7
    assert abs(T[2, 2]) < 0.1


def _digest(root: Path) -> dict[str, str]:
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


def test_same_seed_same_bytes(tmp_path):
    a = synthesize(tmp_path / "a", preset="kitti-like", seed=7, frames=2, scale=0.2, progress=False, road_after=25.0)
    b = synthesize(tmp_path / "b", preset="kitti-like", seed=7, frames=2, scale=0.2, progress=False, road_after=25.0)
    c = synthesize(tmp_path / "c", preset="kitti-like", seed=8, frames=2, scale=0.2, progress=False, road_after=25.0)
    da, db, dc = _digest(a.root), _digest(b.root), _digest(c.root)
    assert len(da) > 8 and da == db
    assert da["images/CAM_FRONT/000000.png"] != dc["images/CAM_FRONT/000000.png"]
    assert not list(tmp_path.glob(".*partial*"))  # no temporary folder left behind
    with pytest.raises(PavemapError, match="already exists"):
        synthesize(tmp_path / "a", preset="kitti-like", seed=7, frames=2, scale=0.2, progress=False, road_after=25.0)


def test_cli_synth(tmp_path):
    from typer.testing import CliRunner

    from pavemap.cli import app

    out = tmp_path / "cli_seq"
    res = CliRunner().invoke(app, ["synth", "--preset", "kitti-like", "--seed", "4", "--frames", "2", "--scale",
                                   "0.15", "--depth", "dense", "--defect-density", "30", "--out", str(out)])
    assert res.exit_code == 0, res.output
    seq = read_sequence(out)
    assert len(seq.frames) == 2
    d = load_depth(out / seq.frames[0].views["CAM_FRONT"].depth)
    sem = load_semantics(out / seq.frames[0].views["CAM_FRONT"].semantics)
    assert ((d > 0) == (sem != 7)).mean() > 0.99  # dense: depth wherever something was hit
    res = CliRunner().invoke(app, ["synth", "--preset", "nope", "--out", str(tmp_path / "x")])
    assert res.exit_code != 0


def test_cli_synth_clean_then_damaged(tmp_path):
    """`pavemap synth --defect-free-until M`: no defect centred in the first M metres along the drive (the
    clean stretch of a clean-then-damaged drive); the same world without it has defects there."""
    from typer.testing import CliRunner

    from pavemap.cli import app

    out = tmp_path / "half"
    res = CliRunner().invoke(app, ["synth", "--preset", "kitti-like", "--seed", "2", "--frames", "2", "--scale",
                                   "0.1", "--depth", "none", "--defect-density", "60", "--defect-free-until", "30",
                                   "--out", str(out)])
    assert res.exit_code == 0, res.output
    world = load_world(out)
    assert world.params.defect_free_until_m == 30.0
    truth = load_truth_defects(out)
    xy = np.array([[t.properties["x_m"], t.properties["y_m"]] for t in truth])
    s, _ = world.st_at(xy[:, 0], xy[:, 1])
    assert len(truth) >= 10 and s.min() >= world.params.road_before + 30.0 - 0.5  # st raster: 0.5 m cells
    everywhere = make_world("kitti-like", 2, frames=2, defect_density=60.0)
    s_all = np.array([everywhere.st_at(np.array([d["centre"][0]]), np.array([d["centre"][1]]))[0][0]
                      for d in everywhere.defects])
    assert (s_all < world.params.road_before + 30.0 - 0.5).sum() >= 5


def test_synth_on_a_missing_gpu_is_a_clear_error(tmp_path, monkeypatch):
    import torch
    from typer.testing import CliRunner

    from pavemap.cli import app

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)  # the same on a machine with a GPU
    res = CliRunner().invoke(app, ["synth", "--out", str(tmp_path / "x"), "--frames", "1", "--device", "cuda"])
    assert res.exit_code == 2, res.output
    assert "error: device 'cuda'" in res.output and "CUDA" in res.output
    assert not (tmp_path / "x").exists()


def test_exposure_drift_stays_bounded_on_a_kilometres_long_drive():
    from pavemap.synth.generate import exposure_drift

    rng = np.random.default_rng(3)
    long = np.log(exposure_drift(rng.normal(0, 0.04, 4541)))  # KITTI-00's length
    assert long.std() < 0.4 and np.abs(long).max() < 1.2  # a plain walk reaches ~2.7 here (15x gains)
    steps = rng.normal(0, 0.04, 24)
    short = np.log(exposure_drift(steps))
    walk = np.cumsum(steps)
    assert np.abs(short - (walk - walk.mean())).max() < 0.03  # a short drive drifts as before
    assert exposure_drift(np.zeros(0)).shape == (0,)
