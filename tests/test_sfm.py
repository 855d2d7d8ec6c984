"""Poses from plain images with pycolmap SfM, metric scale from the camera mounting height."""

from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("pycolmap")

from pavemap.errors import PavemapError  # noqa: E402
from pavemap.io.folder import import_folder  # noqa: E402
from pavemap.io.sequence import read_sequence  # noqa: E402
from pavemap.io.sfm import sfm_poses  # noqa: E402

MOUNT_HEIGHT = 1.65  # the kitti-like rig's camera height above the road (synth/rig.py)


def _rigid_align_error(est: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """Per-frame position error after the best rotation + translation (no scale: scale is under test)."""
    ce, cg = est.mean(0), gt.mean(0)
    U, _, Vt = np.linalg.svd((gt - cg).T @ (est - ce))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ D @ Vt
    return np.linalg.norm((est - ce) @ R.T + cg - gt, axis=1)


@pytest.mark.slow
def test_sfm_trajectory_on_synthetic_kitti_drive(tmp_path):
    from pavemap.synth import synthesize

    truth = synthesize(tmp_path / "truth", preset="kitti-like", seed=0, frames=30, scale=0.5, depth="none",
                       progress=False)
    cam = truth.cameras["CAM_FRONT"]
    (tmp_path / "cameras.json").write_text(json.dumps(
        {"cameras": {"CAM_FRONT": {"width": cam.width, "height": cam.height, "K": cam.K.tolist()}}}))
    seq = import_folder(tmp_path / "truth" / "images" / "CAM_FRONT", tmp_path / "cameras.json", "sfm",
                        tmp_path / "seq", camera_height=MOUNT_HEIGHT)
    s = read_sequence(tmp_path / "seq")
    assert len(s.frames) == len(truth.frames)  # every frame registered
    est = np.stack([f.views["CAM_FRONT"].T_world_cam[:3, 3] for f in s.frames])
    gt = np.stack([f.views["CAM_FRONT"].T_world_cam[:3, 3] for f in truth.frames])
    path = float(np.linalg.norm(np.diff(gt, axis=0), axis=1).sum())
    err = _rigid_align_error(est, gt)
    rmse_pct = 100 * float(np.sqrt((err**2).mean())) / path
    scale_ratio = float(np.linalg.norm(np.diff(est, axis=0), axis=1).sum()) / path
    print(f"\nSfM trajectory: RMSE {rmse_pct:.2f} % of {path:.1f} m path, max {err.max():.3f} m, "
          f"path-length ratio {scale_ratio:.4f}")
    assert rmse_pct <= 2.0
    assert abs(scale_ratio - 1) < 0.05
    # z-up metric world with the road at z ~ 0: cameras at the mounting height, looking forward
    assert np.all(np.abs(est[:, 2] - MOUNT_HEIGHT) < 0.2)
    R0 = s.frames[0].views["CAM_FRONT"].T_world_cam[:3, :3]
    assert R0[2, 1] < -0.98  # camera y (down) is world -z
    assert seq.frames[-1].views["CAM_FRONT"].T_world_cam[0, 3] > 20  # drove ~29 m along +x


def test_sfm_rejects_too_few_images(tmp_path):
    from pavemap.types import Camera

    cam = Camera("c", 32, 24, np.array([[30.0, 0, 15.5], [0, 30.0, 11.5], [0, 0, 1]]))
    with pytest.raises(PavemapError, match="at least 3 images"):
        sfm_poses([tmp_path / "a.png", tmp_path / "b.png"], cam)
    with pytest.raises(PavemapError, match="camera height must be positive"):
        sfm_poses([tmp_path / f"{i}.png" for i in range(3)], cam, camera_height=0)
