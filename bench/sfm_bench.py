"""SfM on real clips: ``python bench/sfm_bench.py`` → ``bench/results/sfm.json``.

- ``kitti-odometry-sample`` (51 grey KITTI frames, true poses ignored): trajectory RMSE after a
  similarity alignment to the true poses, as a share of the path; camera height (scale from the
  known 1.65 m, checked against the true trajectory's scale). Target RMSE ≤ 1 %, height 1.65 ± 0.05 m.
- ``nuscenes-front-clip`` (21 colour keyframes, nominal intrinsics, bonnet in view): ego mask found
  automatically and the segmenter's vehicle masks, as the import gives SfM; registered frames, lateral
  deviation of the path from a straight line, camera height
  constancy. Targets: 21/21, ≤ 0.5 m, ± 5 cm.
- ``nuscenes-front-clip-2`` (26 colour keyframes, a turn into an open lot; issue 42): the same figures, and
  which method gave the path (COLMAP or the car's planar motion), what was dropped, the total turn, the camera
  height the dense road points read. Targets: ≥ 90 % of the frames, the turn in the path, height ± 5 cm.

Both report ``road_steps``: each step's length from the road's image motion (``pavemap.sfm.steps``), which
sets the path's scale, beside the SfM's own; KITTI also the camera height the road's steps imply with the true
poses (``road_steps_on_true_poses``).

The clip also reports ``road_sideways``: per step, the sideways offset of the destination camera at which the
road matches best (``pavemap.sfm.steps.road_sideways``), beside the SfM path's own sideways step.

Both also report ``speed_check``: what the importers' speed check (``--fps``; KITTI 10 Hz, the clip's
keyframes 2 Hz) says of the trajectory found: the largest change of speed per second, against its limit.

``stage1`` / ``stage1_2``: the user's whole path on each nuScenes clip, through the CLI: ``import folder --poses
sfm --fps 2`` (the segmenter's semantics and vehicle masks), then ``reconstruct`` with its defaults: frames
kept, other parts, the speed check's reading, stage 1's camera height and held-out PSNR (over the road the
training views textured, with that share and the PSNR over every covered road pixel beside it).

Data: ``../shared/data`` (``PAVEMAP_DATA`` overrides). Run it niced: it uses the CPU for minutes.
"""

from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

import numpy as np
from PIL import Image

from common import git_commit  # bench/ is the script's folder
from pavemap.io.egomask import detect_ego_mask, mask_report
from pavemap.segment.movers import movable_masks
from pavemap.sfm.checks import SfmChecks, path_acceleration
from pavemap.sfm.pipeline import sfm_poses
from pavemap.types import Camera

DATA = Path(os.environ.get("PAVEMAP_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))
OUT = Path(__file__).resolve().parent / "results" / "sfm.json"


def umeyama(X: np.ndarray, Y: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Similarity (s, R, t) with Y ≈ s R X + t for point sets (N, 3)."""
    mx, my = X.mean(0), Y.mean(0)
    Xc, Yc = X - mx, Y - my
    U, S, Vt = np.linalg.svd(Yc.T @ Xc / len(X))
    D = np.eye(3)
    D[2, 2] = np.sign(np.linalg.det(U @ Vt))
    R = U @ D @ Vt
    s = float(np.trace(np.diag(S) @ D) / ((Xc**2).sum() / len(X)))
    return s, R, my - s * R @ mx


def speed_check(res, hz: float) -> dict:
    """The speed check ``import folder --fps HZ`` / ``import video`` apply (the SfM here runs without frame
    times so that a refused clip still gives its figures): the largest change of speed per second over the
    registered frames at their true times, against the check's limit."""
    checks = SfmChecks()
    reg = np.flatnonzero(res.registered)
    got = path_acceleration(res.T_world_cam[reg, :3, 3], reg / hz, checks.accel_window_s)
    if got is None:
        return {"hz": hz, "max_accel_mps2": None, "passes": True, "note": "drive shorter than two windows"}
    return {"hz": hz, "max_accel_mps2": round(got[0], 2), "at_s": round(got[1], 2),
            "limit_mps2": checks.max_accel_mps2, "passes": bool(got[0] <= checks.max_accel_mps2)}


def kitti() -> dict:
    root = DATA / "kitti-odometry-sample"
    ims = sorted((root / "sequences/90/image_0").glob("*.png"))
    P0 = np.array((root / "sequences/90/calib.txt").read_text().splitlines()[0].split()[-12:], float).reshape(3, 4)
    W, H = Image.open(ims[0]).size
    cam = Camera("cam0", W, H, P0[:, :3].copy())
    t = time.time()
    mask = detect_ego_mask(ims, W, H)
    res = sfm_poses(ims, cam, camera_height=1.65, ego_mask=mask if mask.any() else None)
    dt = time.time() - t
    gt = np.loadtxt(root / "poses/90.txt").reshape(-1, 3, 4)
    reg = np.flatnonzero(res.registered)
    X, Y = res.T_world_cam[reg, :3, 3], gt[reg, :, 3]
    s, R, tt = umeyama(X, Y)
    rmse = float(np.sqrt((((s * (R @ X.T)).T + tt - Y) ** 2).sum(1).mean()))
    path = float(np.linalg.norm(np.diff(gt[:, :, 3], axis=0), axis=1).sum())
    return {"frames": len(ims), "registered": int(res.registered.sum()), "rmse_m": round(rmse, 3),
            "path_m": round(path, 2), "rmse_share": round(rmse / path, 4),
            # the SfM world is metric by the 1.65 m prior; the similarity to the truth says how right that was
            "camera_height_m": round(1.65 * s, 3), "scale_to_truth": round(s, 4),
            "ego_mask": mask_report(mask, "auto").to_dict(), "checks": res.info["checks"],
            "K_used": res.info["K_refined"],
            "dense_scale": res.info.get("dense_scale"),
            "road_steps": res.info.get("road_steps"), "speed_check": speed_check(res, 10.0),
            "seconds": round(dt, 1), "road_steps_on_true_poses": kitti_true_pose_steps(ims, cam, gt)}


def kitti_true_pose_steps(ims: list[Path], cam: Camera, gt: np.ndarray) -> dict:
    """The road's step lengths with the *true* poses at the nominal 1.65 m: the camera height they imply
    (true step / road step × 1.65), an estimate independent of the triangulated ground points."""
    from pavemap.io.kitti import kitti_to_world
    from pavemap.sfm.steps import road_steps

    T_kitti = np.tile(np.eye(4), (len(gt), 1, 1))
    T_kitti[:, :3, :] = gt
    T = kitti_to_world(T_kitti, np.zeros(3))  # cam0 in pavemap's z-up world
    est = road_steps(ims, T, cam, 1.65)
    true = np.linalg.norm(np.diff(T[:, :3, 3], axis=0), axis=1)
    ok = np.array([e.trusted for e in est])
    h = 1.65 * true[ok] / np.array([e.length_m for e in est])[ok]
    half = len(est) // 2
    return {"measured": int(ok.sum()), "steps": len(est), "implied_height_median_m": round(float(np.median(h)), 3),
            "implied_height_p10_p90_m": [round(float(np.percentile(h, q)), 3) for q in (10, 90)],
            "first_half_m": round(float(np.median(h[np.flatnonzero(ok) < half])), 3),
            "second_half_m": round(float(np.median(h[np.flatnonzero(ok) >= half])), 3)}


def nuscenes(clip: str = "nuscenes-front-clip") -> dict:
    root = DATA / clip
    ims = sorted((root / "images").glob("*.jpg"))
    c = json.loads((root / "cameras.json").read_text())["cameras"]["front"]
    cam = Camera("front", c["width"], c["height"], np.array(c["K"], float))
    t = time.time()
    mask = detect_ego_mask(ims, cam.width, cam.height)
    # the segmenter's vehicle and people masks, as the user's import gives SfM (`import folder --poses sfm`)
    movers, _ = movable_masks("auto")
    res = sfm_poses(ims, cam, camera_height=1.5, ego_mask=mask, refine_intrinsics=True, movers=movers)
    dt = time.time() - t
    dense = res.info.get("dense_scale") or {}
    C = res.T_world_cam[res.registered, :3, 3]
    d = C[-1, :2] - C[0, :2]
    d /= np.linalg.norm(d)
    lateral = (C[:, :2] - C[0, :2]) @ np.array([-d[1], d[0]])
    rng = res.info["checks"]["height_range_m"]
    return {"frames": len(ims), "registered": int(res.registered.sum()),
            "path_m": round(float(np.linalg.norm(np.diff(C, axis=0), axis=1).sum()), 2),
            "lateral_max_m": round(float(np.abs(lateral).max()), 3),
            "camera_height_range_m": rng,
            "camera_height_halfrange_m": None if rng is None else round((rng[1] - rng[0]) / 2, 3),
            "ego_mask": mask_report(mask, "auto").to_dict(), "K_nominal": {"fx": 1266.417, "cx": 816.267,
                                                                          "cy": 491.507},
            "K_refined": res.info.get("K_refined"), "intrinsics_refinement": res.info.get("intrinsics_refinement"),
            "method": res.info.get("method"), "dropped": res.info.get("dropped"), "parts": res.info.get("parts"),
            "scale_source": res.info.get("scale_source"), "alternatives": res.info.get("alternatives"),
            "reverse": (res.info.get("planar") or {}).get("reverse", res.info.get("steps", {}).get("reverse")),
            "planar_yaw_total_deg": round(sum((res.info.get("planar") or {}).get("yaw_deg", [0.0])), 1),
            "camera_height_by_dense_points_m": dense.get("median"),
            "checks": res.info["checks"], "interpolated": res.info["interpolated"],
            "steps_m": np.linalg.norm(np.diff(C, axis=0), axis=1).round(2).tolist(),
            "dense_scale": res.info.get("dense_scale"), "road_steps": res.info.get("road_steps"),
            "speed_check": speed_check(res, 2.0),
            "road_sideways": sideways(ims, res, cam, 1.5, mask, lateral),
            "movers": res.info.get("movers"), "seconds": round(dt, 1)}


def sideways(ims: list[Path], res, cam: Camera, h: float, mask, lateral: np.ndarray) -> dict:  # noqa: ANN001
    """The road's check of the path's sideways motion (:func:`pavemap.sfm.steps.road_sideways`): per
    moving step the sideways offset (m) at which the road matches best, and the SfM's own sideways step
    (``lateral`` (R,) the registered path's offsets from its chord, m)."""
    from pavemap.sfm.steps import road_sideways

    reg = np.flatnonzero(res.registered)
    k = res.info.get("K_refined") or {}
    K = cam.K.copy()
    if k:
        K[0, 0], K[1, 1], K[0, 2], K[1, 2] = k["fx"], k["fy"], k["cx"], k["cy"]
    rows = road_sideways([ims[i] for i in reg], res.T_world_cam[reg], Camera(cam.name, cam.width, cam.height, K),
                         h, mask)
    sfm_side = np.diff(lateral)
    for r in rows:
        r["sfm_sideways_m"] = round(float(sfm_side[r["step"]]), 3)
    got = [r for r in rows if r["best_offset_m"] is not None]
    return {"steps": rows, "compared": len(got),
            "within_5cm": sum(abs(r["best_offset_m"]) <= 0.05 for r in got),
            "max_abs_offset_m": max((abs(r["best_offset_m"]) for r in got), default=None)}


def synthetic_steps() -> dict:
    """The road's step lengths against the truth on the synthetic presets' front cameras (true poses, the true
    camera height over the road): relative error per step. Drives from ``mesh_bench`` (PAVEMAP_BENCH_DATA)."""
    from mesh_bench import bench_drive, truth_camera_height
    from pavemap.io.sequence import read_sequence
    from pavemap.sfm.steps import road_steps

    out = {}
    for preset in ("kitti-like", "nuscenes-like"):
        data = Path(os.environ.get("PAVEMAP_BENCH_DATA", "/tmp/pavemap-bench"))
        seq = read_sequence(bench_drive(data, preset, "none", "cpu"))
        cam = seq.cameras["CAM_FRONT"]
        views = [f.views[cam.name] for f in seq.frames if cam.name in f.views][:40]
        T = np.stack([v.T_world_cam for v in views])
        true = np.linalg.norm(np.diff(T[:, :3, 3], axis=0), axis=1)
        h = truth_camera_height(seq, cam.name)
        t = time.time()
        est = road_steps([seq.root / v.image for v in views], T, cam, h)
        ok = np.array([e.trusted for e in est])
        err = np.array([e.length_m for e in est])[ok] / true[ok] - 1
        out[preset] = {
            "steps": len(est), "measured": int(ok.sum()), "camera_height_m": round(h, 3),
            "true_step_m": [round(float(true.min()), 2), round(float(true.max()), 2)],
            "signed_median": round(float(np.median(err)), 4), "abs_median": round(float(np.median(abs(err))), 4),
            "abs_p90": round(float(np.percentile(abs(err), 90)), 4), "abs_max": round(float(abs(err).max()), 4),
            "seconds": round(time.time() - t, 1)}
    return out


def stage1(clip: str) -> dict:
    """Import a clip with SfM and reconstruct it, as a user does (one process per command)."""
    import subprocess
    import tempfile

    root = DATA / clip
    cli = [sys.executable, "-c", "import sys; from pavemap.cli import main; sys.exit(main())"]
    with tempfile.TemporaryDirectory(prefix="pavemap-sfm-bench-") as td:
        seq, mesh = Path(td) / "seq", Path(td) / "mesh"
        t = time.time()
        subprocess.run(cli + ["import", "folder", str(root / "images"), "--cameras", str(root / "cameras.json"),
                              "--poses", "sfm", "--fps", "2", "--out", str(seq)], check=True, capture_output=True)
        t_import = time.time() - t
        subprocess.run(cli + ["reconstruct", str(seq), "--out", str(mesh)], check=True, capture_output=True)
        sfm = json.loads((seq / "sfm.json").read_text())
        m = json.loads((mesh / "metrics.json").read_text())
    ck = sfm.get("checks") or {}
    return {"command": f"pavemap import folder {clip}/images --poses sfm --fps 2; pavemap reconstruct",
            "frames": sfm.get("images"), "registered": sfm.get("registered"), "method": sfm.get("method"),
            "other_parts": sfm.get("other_parts"), "max_accel_mps2": ck.get("max_accel_mps2"),
            "accel_unchecked": ck.get("accel_unchecked"), "import_seconds": round(t_import, 1),
            # the camera's height over the road along the path, as the user's import measured it (vehicle masks)
            "camera_heights_m": ck.get("heights_m"), "camera_height_range_m": ck.get("height_range_m"),
            "camera_height_p10_p90_m": ck.get("height_p10_p90_m"), "heights_measured": ck.get("heights_measured"),
            "camera_height_by_dense_points_m": (sfm.get("dense_scale") or {}).get("median"),
            "camera_height_stage1_m": m.get("camera_height_init"), "heldout_frames_every": 10,
            "psnr_heldout_db": m.get("psnr"), "heldout_textured_share": m.get("heldout_textured_share"),
            "psnr_heldout_all_covered_db": m.get("psnr_untextured_included"), "coverage": m.get("coverage"),
            "stage1_seconds": m.get("seconds")}


def main() -> None:
    """``python bench/sfm_bench.py [kitti] [nuscenes] [nuscenes2] [synthetic] [stage1] [stage1_2]``: the named
    parts (default all),
    merged into the results; each part records the commit and the machine's load."""
    names = sys.argv[1:] or ["kitti", "nuscenes", "nuscenes2", "synthetic", "stage1", "stage1_2"]
    out = json.loads(OUT.read_text()) if OUT.is_file() else {}
    parts = (("kitti", kitti), ("nuscenes", nuscenes), ("nuscenes2", lambda: nuscenes("nuscenes-front-clip-2")),
             ("synthetic", synthetic_steps), ("stage1", lambda: stage1("nuscenes-front-clip")),
             ("stage1_2", lambda: stage1("nuscenes-front-clip-2")))
    for name, fn in parts:
        if name not in names:
            continue
        try:
            out[name] = fn()
            out[name]["commit"] = git_commit()
            out[name]["load_1min"] = round(os.getloadavg()[0], 2)
        except Exception as e:  # report the failure as a figure: the benchmark is the place to see it
            out[name] = {"error": f"{type(e).__name__}: {e}"}
        print(name, json.dumps(out[name]), flush=True)
    OUT.parent.mkdir(parents=True, exist_ok=True)
    OUT.write_text(json.dumps(out, indent=1) + "\n")
    print(f"wrote {OUT}", file=sys.stderr)


if __name__ == "__main__":
    main()
