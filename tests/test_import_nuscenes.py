"""nuScenes importer on a minimal dataset in the devkit's table format, loaded by the real devkit."""

from __future__ import annotations

import json

import numpy as np
import pytest
from PIL import Image

pytest.importorskip("nuscenes")
from pyquaternion import Quaternion  # noqa: E402  (a devkit dependency: an independent quaternion path)
from scipy.spatial.transform import Rotation  # noqa: E402

from pavemap.errors import PavemapError  # noqa: E402
from pavemap.io.nuscenes import CAMERAS, import_nuscenes  # noqa: E402
from pavemap.io.sequence import SequenceError, read_sequence  # noqa: E402

VERSION = "v1.0-mini"
W, H = 64, 36
YAW = {"CAM_FRONT": 0, "CAM_FRONT_RIGHT": -55, "CAM_BACK_RIGHT": -110, "CAM_BACK": 180,
       "CAM_BACK_LEFT": 110, "CAM_FRONT_LEFT": 55}
R_CAM_TO_EGO = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], dtype=float)  # OpenCV camera looking along ego +x


def _q(R: np.ndarray) -> list[float]:
    x, y, z, w = Rotation.from_matrix(R).as_quat()
    return [float(w), float(x), float(y), float(z)]


def write_dataset(root, n_samples=3, sweeps=True):
    t = root / VERSION
    t.mkdir(parents=True)
    (root / "maps").mkdir()
    Image.fromarray(np.zeros((4, 4), np.uint8)).save(root / "maps" / "map0.png")
    rng = np.random.default_rng(0)
    tables = {k: [] for k in ("category", "attribute", "visibility", "instance", "sensor", "calibrated_sensor",
                              "ego_pose", "log", "scene", "sample", "sample_data", "sample_annotation", "map")}
    tables["category"].append({"token": "cat0", "name": "vehicle.car", "description": ""})
    tables["log"].append({"token": "log0", "logfile": "l", "vehicle": "n015", "date_captured": "2018-07-24",
                          "location": "singapore-onenorth"})
    tables["map"].append({"token": "map0", "log_tokens": ["log0"], "category": "semantic_prior",
                          "filename": "maps/map0.png"})
    for c in CAMERAS:
        tables["sensor"].append({"token": f"s_{c}", "channel": c, "modality": "camera"})
        yaw = np.radians(YAW[c])
        Rz = Rotation.from_euler("z", yaw).as_matrix()
        Rtilt = Rotation.from_euler("x", np.radians(2.0)).as_matrix()  # a small pitch of the camera
        tables["calibrated_sensor"].append({
            "token": f"cs_{c}", "sensor_token": f"s_{c}",
            "translation": [1.5 * np.cos(yaw), 0.5 * np.sin(yaw), 1.55],
            "rotation": _q(Rz @ R_CAM_TO_EGO @ Rtilt),
            "camera_intrinsic": [[50.0, 0, 31.5], [0, 50.0, 17.5], [0, 0, 1]],
        })
    for si, (name, n) in enumerate((("scene-0061", 1), ("scene-0064", n_samples))):
        sample_tokens = [f"smp{si}_{k}" for k in range(n)]
        tables["scene"].append({"token": f"sc{si}", "log_token": "log0", "nbr_samples": n,
                                "first_sample_token": sample_tokens[0], "last_sample_token": sample_tokens[-1],
                                "name": name, "description": ""})
        base = 1_532_402_927_000_000 + si * 100_000_000
        for k, tok in enumerate(sample_tokens):
            tables["sample"].append({"token": tok, "timestamp": base + k * 500_000, "scene_token": f"sc{si}",
                                     "prev": sample_tokens[k - 1] if k else "",
                                     "next": sample_tokens[k + 1] if k + 1 < n else ""})
        for c in CAMERAS:
            chain = []
            for k in range(n):
                chain.append((k, True))
                if sweeps and k + 1 < n:
                    chain.append((k + 0.5, False))
            toks = [f"sd{si}_{c}_{j}" for j in range(len(chain))]
            for j, (kk, key) in enumerate(chain):
                ts = base + int(kk * 500_000) + 3_000 * CAMERAS.index(c)
                ep = f"ep_{toks[j]}"
                heading = 0.3 + 0.05 * kk
                tables["ego_pose"].append({
                    "token": ep, "timestamp": ts,
                    "translation": [400.0 + 4.0 * kk, 1100.0 + 1.0 * kk, 0.02 * kk],
                    "rotation": _q(Rotation.from_euler("z", heading).as_matrix()),
                })
                fn = f"{'samples' if key else 'sweeps'}/{c}/n015-{toks[j]}.jpg"
                (root / fn).parent.mkdir(parents=True, exist_ok=True)
                Image.fromarray(rng.integers(0, 255, (H, W, 3), dtype=np.uint8)).save(root / fn)
                tables["sample_data"].append({
                    "token": toks[j], "sample_token": sample_tokens[int(np.ceil(kk))], "ego_pose_token": ep,
                    "calibrated_sensor_token": f"cs_{c}", "timestamp": ts, "fileformat": "jpg",
                    "is_key_frame": key, "height": H, "width": W, "filename": fn,
                    "prev": toks[j - 1] if j else "", "next": toks[j + 1] if j + 1 < len(toks) else "",
                })
    for k, v in tables.items():
        (t / f"{k}.json").write_text(json.dumps(v))
    return root


def _devkit_project(root, sd_token: str, p_global: np.ndarray) -> np.ndarray:
    """Project a global point the devkit way (pyquaternion, ego pose then calibrated sensor)."""
    tables = {k: {r["token"]: r for r in json.loads((root / VERSION / f"{k}.json").read_text())}
              for k in ("sample_data", "ego_pose", "calibrated_sensor")}
    sd = tables["sample_data"][sd_token]
    ep = tables["ego_pose"][sd["ego_pose_token"]]
    cs = tables["calibrated_sensor"][sd["calibrated_sensor_token"]]
    p = Quaternion(ep["rotation"]).inverse.rotate(p_global - np.array(ep["translation"]))
    p = Quaternion(cs["rotation"]).inverse.rotate(p - np.array(cs["translation"]))
    u = np.array(cs["camera_intrinsic"]) @ p
    return u[:2] / u[2]


def _our_project(seq, origin, frame: int, cam: str, p_global: np.ndarray) -> np.ndarray:
    v = seq.frames[frame].views[cam]
    Xc = np.linalg.inv(v.T_world_cam) @ np.append(p_global - origin, 1.0)
    u = seq.cameras[cam].K @ Xc[:3]
    return u[:2] / u[2]


def test_keyframes_six_cameras(tmp_path):
    root = write_dataset(tmp_path / "nus")
    seq = import_nuscenes(root, "scene-0064", tmp_path / "seq", version=VERSION)
    s = read_sequence(tmp_path / "seq")
    assert len(s.frames) == 3 and sorted(s.cameras) == sorted(CAMERAS)
    assert np.allclose(s.cameras["CAM_FRONT"].K, [[50, 0, 31.5], [0, 50, 17.5], [0, 0, 1]])
    origin = np.array([400.0, 1100.0, 0.0])  # first ego position of the scene
    rng = np.random.default_rng(1)
    for k in range(3):
        for c in CAMERAS:
            # a point 10 m in front of this camera, so it projects inside the image
            v = s.frames[k].views[c]
            Xc = np.array([rng.uniform(-2, 2), rng.uniform(-1, 1), 10.0])
            pg = (v.T_world_cam @ np.append(Xc, 1))[:3] + origin
            np.testing.assert_allclose(_our_project(s, origin, k, c, pg),
                                       _devkit_project(root, f"sd1_{c}_{2 * k}", pg), atol=1e-6)
    # z up: every camera's optical axis is near-horizontal, its image y axis points down
    for c in CAMERAS:
        R = s.frames[0].views[c].T_world_cam[:3, :3]
        assert abs(R[2, 2]) < 0.1 and R[2, 1] < -0.99
    np.testing.assert_allclose(s.frames[0].views["CAM_FRONT"].T_world_cam[2, 3], 1.55, atol=1e-6)
    assert s.frames[0].timestamp == 0.0 and abs(s.frames[2].timestamp - 1.0) < 1e-3
    # geo origin: 400 m east, 1100 m north of the onenorth reference
    g = s.geo_origin
    assert g is not None and abs(g.lat - (1.2882100868743724 + 1100 / 110574.0)) < 1e-4
    assert abs(g.lon - (103.78475189208984 + 400 / (111320.0 * np.cos(np.radians(1.29))))) < 1e-4
    assert seq.name == "scene-0064"


def test_sweeps_and_camera_subset(tmp_path):
    root = write_dataset(tmp_path / "nus")
    s = import_nuscenes(root, "scene-0064", tmp_path / "seq", version=VERSION, sweeps=True,
                        cameras=["CAM_FRONT", "CAM_BACK"])
    assert len(s.frames) == 5 and sorted(s.cameras) == ["CAM_BACK", "CAM_FRONT"]
    xs = [f.views["CAM_FRONT"].T_world_cam[0, 3] for f in s.frames]
    assert np.all(np.diff(xs) > 0)  # the sweeps sit between keyframes along the drive


def test_bad_inputs(tmp_path):
    root = write_dataset(tmp_path / "nus", sweeps=False)
    with pytest.raises(PavemapError, match=r"'scene-9999'.*valid scenes: scene-0061, scene-0064"):
        import_nuscenes(root, "scene-9999", tmp_path / "seq", version=VERSION)
    with pytest.raises(SequenceError, match=r"'v1.0-trainval' not found; available: \['v1.0-mini'\]"):
        import_nuscenes(root, "scene-0064", tmp_path / "seq", version="v1.0-trainval")
    with pytest.raises(PavemapError, match="CAM_TOP"):
        import_nuscenes(root, "scene-0064", tmp_path / "seq", version=VERSION, cameras=["CAM_TOP"])
    img = next((root / "samples" / "CAM_BACK").iterdir())
    img.unlink()
    with pytest.raises(SequenceError, match="image not found"):
        import_nuscenes(root, "scene-0064", tmp_path / "seq", version=VERSION)


def test_cli_import_nuscenes(tmp_path):
    from typer.testing import CliRunner

    from pavemap.cli import app

    root = write_dataset(tmp_path / "nus", sweeps=False)
    r = CliRunner().invoke(app, ["import", "nuscenes", str(root), "--scene", "scene-0064", "--cameras",
                                 "CAM_FRONT,CAM_BACK", "--no-semantics", "--out", str(tmp_path / "seq")])
    assert r.exit_code == 0, r.output
    assert "scene-0064: 3 frames, 6 views, semantics: none" in r.output
    assert sorted(read_sequence(tmp_path / "seq").cameras) == ["CAM_BACK", "CAM_FRONT"]
