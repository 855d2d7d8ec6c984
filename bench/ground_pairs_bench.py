"""The view of a pair the ground points match from: ``python bench/ground_pairs_bench.py`` -> ``ground_pairs.json``.

Stage 1's ground points (:mod:`pavemap.mesh.ground_points`) match each view pair once. Before ed3365e the
reference was the earlier view of a pair and its partners the later ones; a drive going forwards then matches
from the view behind, whose near road the view ahead cannot see, and a clip numbered backwards from the view
ahead (the shared nuScenes clips: 56 vs 213 dense road points on the same clip in its two orders). Since
ed3365e a pair is matched from the view whose ground the other sees more of, the same pairs both ways round.
Per synthetic drive without depth (kitti-like and nuScenes-like, seeds 0-2, the presets' own size) and rule:
the ground points (count, robust RMS of their height error against the true surface, each camera's height
error), then stage 1 with its defaults (height RMSE over all and over observed vertices, held-out PSNR,
seconds); and the real KITTI sample with its true poses (points, the camera height they give; true ~1.65 m).
Run it niced: ~10 minutes of CPU.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))

from common import git_commit, machine_entry, write_results  # noqa: E402
from mesh_bench import SETTINGS, truth_camera_height  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results" / "ground_pairs.json"


def partners_from_behind(vds, i: int, cfg) -> list[int]:  # noqa: ANN001
    """The rule before ed3365e: the later views within ``max_gap`` frames that see enough of i's ground."""
    from pavemap.mesh import ground_points as gpm

    a, out = vds[i], []
    for j in range(i + 1, len(vds)):
        b = vds[j]
        if b.pos - a.pos > cfg.max_gap or len(out) >= cfg.max_partners:
            break
        if np.linalg.norm(b.T[:3, 3] - a.T[:3, 3]) < 0.05 or b.img is None:
            continue
        if gpm._overlap_between(a, b, cfg) >= cfg.min_overlap:
            out.append(j)
    return out


def _points(seq, prior: float, truth) -> dict:  # noqa: ANN001
    from pavemap.geometry.triangulate import sample_grid
    from pavemap.mesh.config import GroundConfig
    from pavemap.mesh.ground_points import estimate_camera_height, find_ground_points

    t = time.perf_counter()
    gp = find_ground_points(seq, GroundConfig(prior_height=prior))
    r = {"points": len(gp), "seconds": round(time.perf_counter() - t, 1), "cameras": {}}
    for name, e in estimate_camera_height(seq, gp).items():
        true = truth_camera_height(seq, name) if truth is not None else None
        r["cameras"][name] = {"found_m": round(e.median, 4) if e.observable else None,
                              "error_m": round(e.median - true, 4) if e.observable and true else None}
    if truth is not None and len(gp):
        err = gp.points[:, 2] - sample_grid(*truth, gp.points[:, :2])
        r["height_error_robust_rms_m"] = round(float(1.4826 * np.nanmedian(np.abs(err - np.nanmedian(err)))), 4)
    return r


def _stage1(seq, preset: str) -> dict:  # noqa: ANN001
    from pavemap.mesh import reconstruct
    from pavemap.mesh.config import MeshConfig

    st = SETTINGS[preset]
    cfg = MeshConfig.preset(st["mesh_preset"])
    cfg.render_scale, cfg.eval_scale, cfg.device, cfg.resume, cfg.threads = st["render_scale"], 0.25, "cpu", False, 1
    t = time.perf_counter()
    _, m = reconstruct(seq, None, cfg, progress=False)
    return {"height_rmse_m": round(m["height_rmse"], 4), "height_rmse_seen_m": round(m["height_rmse_seen"], 4),
            "psnr_db": round(m["psnr"], 2), "seconds": round(time.perf_counter() - t, 1)}


def main() -> None:
    from pavemap.geometry.grid import GridSpec
    from pavemap.io.sequence import read_sequence
    from pavemap.mesh import ground_points as gpm
    from pavemap.synth import synthesize

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=Path("/tmp/pavemap-bench/ground-pairs"))
    ap.add_argument("--kitti", type=Path, default=Path("/tmp/pavemap-ground/kitti-real"),
                    help="the KITTI sample as bench/ground_bench.py imports it (skipped when missing)")
    ap.add_argument("--results", type=Path, default=RESULTS)
    args = ap.parse_args()
    shipped = gpm._partners
    rules = {"from_behind_before_ed3365e": partners_from_behind, "from_the_view_seen_more_shipped": shipped}
    drives = {}
    for preset in ("kitti-like", "nuscenes-like"):
        for seed in (0, 1, 2):
            p = args.data / f"{preset}-s{seed}"
            if not (p / "sequence.json").is_file():
                synthesize(p, preset, seed=seed, depth="none", progress=False)
            drives[p.name] = (preset, p)
    out: dict = {"commit": git_commit(), "machine": machine_entry(), "drives": {}, "mean": {}}
    for name, (preset, p) in drives.items():
        seq = read_sequence(p)
        grid = GridSpec.from_dict(json.loads((p / "truth" / "height.json").read_text()))
        truth = (grid, np.load(p / "truth" / "height.npy").astype(np.float64))
        prior = 1.65 if preset == "kitti-like" else 1.5
        for rule, fn in rules.items():
            gpm._partners = fn
            try:
                r = {"ground_points": _points(seq, prior, truth), "stage1": _stage1(seq, preset)}
            finally:
                gpm._partners = shipped
            out["drives"].setdefault(name, {})[rule] = r
            print(name, rule, r["ground_points"]["points"], r["stage1"], flush=True)
    for preset in ("kitti-like", "nuscenes-like"):
        for rule in rules:
            rows = [v[rule]["stage1"] for k, v in out["drives"].items() if k.startswith(preset)]
            out["mean"].setdefault(preset, {})[rule] = {
                k: round(float(np.mean([r[k] for r in rows])), 4) for k in ("height_rmse_m", "height_rmse_seen_m",
                                                                            "psnr_db", "seconds")}
    if (args.kitti / "sequence.json").is_file():
        seq = read_sequence(args.kitti)
        for rule, fn in rules.items():
            gpm._partners = fn
            try:
                out.setdefault("kitti_sample_true_poses", {})[rule] = _points(seq, 1.65, None)
            finally:
                gpm._partners = shipped
    write_results(args.results, out)


if __name__ == "__main__":
    main()
