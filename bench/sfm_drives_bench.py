"""SfM on synthetic 2 Hz drives with a known path: ``python bench/sfm_drives_bench.py`` -> ``results/sfm_drives.json``.

Issue 42's synthetic targets: a drive with a 90 deg turn, a stop-and-go drive (and one that creeps in a queue
instead of stopping) and a straight 2 Hz drive register fully and their paths lie within 1 % of the true path after
a similarity alignment. Each drive is rendered with the kitti-like rig at half resolution (620 x 188 px) and with
the nuScenes-like front camera, and posed by each method of :func:`pavemap.sfm.pipeline.sfm_poses`: ``auto``
(COLMAP, once more on thinned keyframes where it fails, then the car's planar motion) and ``planar`` (the planar
motion model alone). Reported per drive and method: frames kept, the RMSE after a similarity (shape) and after a
rigid alignment (shape and metric scale), the scale's error, the source of the scale, seconds. Run it niced: a few
minutes of CPU.
"""

from __future__ import annotations

import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from common import git_commit  # bench/ is the script's folder

OUT = Path(__file__).resolve().parent / "results" / "sfm_drives.json"


def stop_and_go_path() -> np.ndarray:
    """(F, 3): 4 m steps, slowing to a stop of 4 frames (2 s), then away again, on a gentle curve."""
    steps = [4.0] * 5 + [2.5, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 2.5] + [4.0] * 5
    s = np.concatenate([[0.0], np.cumsum(steps)])
    R = 120.0  # a gentle left curve, so the restart is not along the same line
    return np.c_[R * np.sin(s / R), R * (1 - np.cos(s / R)), np.zeros(len(s))]


def creep_path() -> np.ndarray:
    """(F, 3): 4 m steps, slowing to a creep of 0.2-0.3 m steps for 3 s (a queue), then away again, on the
    stop-and-go drive's curve."""
    steps = [4.0] * 5 + [2.5, 1.0, 0.3, 0.2, 0.25, 0.3, 0.2, 1.0, 2.5] + [4.0] * 5
    s = np.concatenate([[0.0], np.cumsum(steps)])
    R = 120.0
    return np.c_[R * np.sin(s / R), R * (1 - np.cos(s / R)), np.zeros(len(s))]


def straight_path(n: int = 20, step: float = 4.0) -> np.ndarray:
    return np.c_[np.arange(n) * step, np.zeros(n), np.zeros(n)]


def similarity(est: np.ndarray, gt: np.ndarray, scale: bool) -> tuple[float, float]:
    """(RMSE in % of the true path, scale factor est -> gt) after the best similarity (or rigid) alignment."""
    me, mg = est.mean(0), gt.mean(0)
    E, G = est - me, gt - mg
    U, S, Vt = np.linalg.svd(G.T @ E / len(E))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    s = float((S * np.diag(D)).sum() / E.var(0).sum()) if scale else 1.0
    err = np.linalg.norm(s * E @ (U @ D @ Vt).T - G, axis=1)
    path = float(np.linalg.norm(np.diff(gt, axis=0), axis=1).sum())
    return 100 * float(np.sqrt((err**2).mean())) / path, s


def render(root: Path, preset: str, path: np.ndarray):  # noqa: ANN201
    from pavemap.synth import synthesize

    # kitti-like at its own size, KITTI's 1241 x 376 (at half of it the turn's feature-poor stretch starves COLMAP)
    scale = 1.0 if preset == "kitti-like" else 0.35
    return synthesize(root, preset=preset, seed=0, frames=len(path), scale=scale, depth="none", progress=False,
                      path=path.tolist(), hz=2.0)


def step_yaw_error(T_est: np.ndarray, T_true: np.ndarray) -> dict:
    """Each step's turn (the change of the camera's heading about the vertical) against the truth's, deg:
    the path's rotations judged step by step, which a similarity fit of the centres can hide by cancelling."""
    def turns(T: np.ndarray) -> np.ndarray:
        fwd = T[:, :3, 2]
        h = np.unwrap(np.arctan2(fwd[:, 1], fwd[:, 0]))
        return np.degrees(np.diff(h))

    err = np.abs(turns(T_est) - turns(T_true))
    return {"mean_deg": round(float(err.mean()), 2), "max_deg": round(float(err.max()), 2)}


def run_drive(truth, method: str) -> dict:  # noqa: ANN001
    from pavemap.sfm.pipeline import sfm_poses
    from pavemap.sfm.result import SfmRefusedError

    cam = truth.cameras["CAM_FRONT"]
    views = [f.views["CAM_FRONT"] for f in truth.frames]
    gt = np.stack([v.T_world_cam[:3, 3] for v in views])
    from mesh_bench import truth_camera_height

    h = truth_camera_height(truth, "CAM_FRONT")  # the mount's height over the true road, as a user would give it
    t = time.time()
    try:
        res = sfm_poses([truth.root / v.image for v in views], cam, camera_height=h, method=method,
                        times=np.array([f.timestamp for f in truth.frames]))
    except SfmRefusedError as e:
        return {"refused": str(e), "seconds": round(time.time() - t, 1)}
    dt = time.time() - t
    k = res.registered
    shape, s = similarity(res.T_world_cam[k, :3, 3], gt[k], True)
    metric, _ = similarity(res.T_world_cam[k, :3, 3], gt[k], False)
    T_true = np.stack([v.T_world_cam for v in views])
    return {"kept": int(k.sum()), "frames": len(k), "method_used": res.info.get("method"),
            "rmse_similarity_pct": round(shape, 3), "rmse_rigid_pct": round(metric, 3),
            "scale_error": round(1 / s - 1, 4), "scale_source": res.info.get("scale_source"),
            "interpolated": res.info.get("interpolated"), "camera_height_m": round(h, 3),
            "colmap_retry": {k: v for k, v in (res.info.get("sfm_retry") or {}).items() if k != "first_try"} or None,
            "step_turn_error": step_yaw_error(res.T_world_cam[k], T_true[k]),
            "road_yaw": {x: (res.info.get("planar") or {}).get("road_yaw", {}).get(x)
                         for x in ("searched", "corrected")},
            "seconds": round(dt, 1)}


def main() -> None:
    from pavemap.synth.trajectory import turn_path

    drives = {"turn_90deg": turn_path(), "stop_and_go": stop_and_go_path(), "creep": creep_path(),
              "straight": straight_path()}
    import argparse

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("presets", nargs="*", help="kitti-like and/or nuscenes-like (default both)")
    presets = ap.parse_args().presets or ["kitti-like", "nuscenes-like"]
    if bad := sorted(set(presets) - {"kitti-like", "nuscenes-like"}):
        ap.error(f"unknown preset(s) {', '.join(bad)}: choose kitti-like, nuscenes-like")
    out: dict = {"what": __doc__.split("\n")[0], "commit": git_commit(),
                 "date": time.strftime("%Y-%m-%d"), "load_1min": round(os.getloadavg()[0], 2), "drives": {}}
    with tempfile.TemporaryDirectory(prefix="pavemap-sfm-drives-") as tmp:
        for preset in presets:
            for name, path in drives.items():
                truth = render(Path(tmp) / f"{preset}-{name}", preset, path)
                row = out["drives"].setdefault(f"{preset}/{name}", {"frames": len(path)})
                for method in ("auto", "planar"):
                    row[method] = run_drive(truth, method)
                    print(preset, name, method, json.dumps(row[method]), flush=True)
    OUT.parent.mkdir(parents=True, exist_ok=True)
    OUT.write_text(json.dumps(out, indent=1) + "\n")
    print(f"wrote {OUT}", file=sys.stderr)


if __name__ == "__main__":
    main()
