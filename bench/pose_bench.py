"""Pose-refinement benchmark: perturb every view of a synthetic drive by a known 0.3 deg / 0.2 m (SPEC §1)
and reconstruct with and without pose refinement.

Writes ``bench/results/pose.json``: per preset, the pose errors (translation m, rotation deg) before and
after, held-out PSNR, height RMSE and seconds for both runs, and the same run on the true poses for reference.
Held-out frames keep their raw perturbed poses plus the correction interpolated from their neighbours; with
independent errors per view that cannot fix them, so their PSNR shows the surface, not the alignment.

    python bench/pose_bench.py [--device cpu|cuda] [--data DIR] [--presets kitti-like,nuscenes-like]
                               [--per view|frame] [--skip-true]
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))

from common import bench_parser, machine_entry, write_results  # noqa: E402
from pavemap.io.sequence import read_sequence  # noqa: E402
from pavemap.mesh import MeshConfig, reconstruct  # noqa: E402
from pavemap.synth import perturb_poses, pose_errors  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "bench" / "results" / "pose.json"
MESH_PRESET = {"nuscenes-like": "nuscenes", "kitti-like": "kitti"}


def _run(seq, preset: str, device: str, refine: bool, epochs: int | None, per: str = "view") -> dict:
    cfg = MeshConfig.preset(MESH_PRESET[preset])
    cfg.device, cfg.resume, cfg.pose_refine, cfg.pose_per = device, False, refine, per
    cfg.threads = 1 if device == "cpu" else None
    if epochs is not None:
        cfg.epochs = epochs
    t = time.perf_counter()
    _, m = reconstruct(seq, None, cfg, progress=False)
    out = {"seconds": round(time.perf_counter() - t, 1), "psnr_db": m["psnr"], "train_psnr_db": m["train_psnr"],
           "sem_acc": m["sem_acc"],
           "height_rmse_m": m.get("height_rmse"), "height_rmse_seen_m": m.get("height_rmse_seen")}
    if refine:
        out["pose_alignment"] = m["pose_alignment"]
        out["refined_poses"] = m["refined_poses"]
    return out


def run_preset(preset: str, data: Path, device: str, epochs: int | None, seed: int, per: str = "view",
               with_true: bool = True) -> dict:
    seq_dir = data / preset
    if not (seq_dir / "sequence.json").is_file():
        from pavemap.synth import synthesize

        synthesize(seq_dir, preset, seed=0, device=device, progress=False)
    seq = read_sequence(seq_dir)
    pert, truth = perturb_poses(seq, 0.3, 0.2, seed=seed, per=per)
    raw = {f"{f.index}/{n}": v.T_world_cam for f in pert.frames for n, v in f.views.items()}
    refined = _run(pert, preset, device, True, epochs, per)
    poses = refined.pop("refined_poses")
    res = {
        "perturbation": {"degrees": 0.3, "metres": 0.2, "seed": seed, "per": per},
        "pose_errors_before": pose_errors({k: raw[k] for k in poses}, truth),
        "pose_errors_after": pose_errors(poses, truth),
        "with_refinement": refined,
        "without_refinement": _run(pert, preset, device, False, epochs),
    }
    if with_true:
        res["true_poses"] = _run(seq, preset, device, False, epochs)
    print(preset, json.dumps(res, indent=1), flush=True)
    return res


def main() -> None:
    ap = bench_parser(__doc__, "kitti-like,nuscenes-like", RESULTS)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--per", default="view", choices=("view", "frame"),
                    help="perturb and refine each camera (view) or each frame's rig as one (frame)")
    ap.add_argument("--skip-true", action="store_true", help="skip the reference run on the true poses")
    a = ap.parse_args()
    results = json.loads(a.results.read_text()) if a.results.is_file() else {}
    key = "cuda" if a.device.startswith("cuda") else "cpu"
    entry = results.get(key, {"presets": {}})
    entry.update(machine_entry())
    for preset in a.presets.split(","):
        name = preset if a.per == "view" else f"{preset} (per frame)"
        entry["presets"][name] = run_preset(preset, a.data, a.device, a.epochs, a.seed, a.per, not a.skip_true)
    results[key] = entry
    write_results(a.results, results)


if __name__ == "__main__":
    main()
