"""Stage-1 benchmark: reconstruct the synthetic nuScenes-like (40 frames x 6 cameras) and KITTI-like drives.

Without depth by default (the monocular case: the geometry comes from ground points triangulated from the
images); ``--depth sparse`` runs the same drive with its LiDAR-like sparse depth (the second column). Both
read one synthesized drive: the no-depth copy is its sequence.json without the depth layer.

Writes ``bench/results/mesh.json`` (merging: each device and depth mode fills its own entry, e.g.
``cpu`` / ``cpu-sparse``). Per preset: seconds per epoch, total seconds, peak RSS, held-out PSNR (road
pixels), semantic accuracy, height RMSE / bias vs truth (all and observed vertices), camera height found vs
true, the run's geometry self-check, renderer throughput (full-view render_view pixels per second).

    python bench/mesh_bench.py [--device cpu|cuda] [--depth none|sparse] [--data DIR] [--presets ...]

Imports only torch / numpy / PIL / scipy (plus trimesh when it is installed, for mesh.ply), so it
runs on a bare GPU machine with ``PYTHONPATH=src``.
"""

from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))

from common import bench_parser, git_commit, machine_entry, no_depth_copy, write_results  # noqa: E402
from pavemap.io.sequence import read_sequence  # noqa: E402
from pavemap.memory import peak_rss_mb  # noqa: E402
from pavemap.mesh import MeshConfig, reconstruct, render_view  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "bench" / "results" / "mesh.json"
TARGETS = {"psnr_db": 26.5, "sem_acc": 0.92, "height_rmse_m": 0.03, "nuscenes_total_s": 300,
           "no_depth": {"camera_height_abs_err_m": 0.02, "height_bias_observed_m": 0.01,
                        "height_rmse_observed_m": 0.03, "time_vs_depth": 1.5}}
PAPER = {"psnr_db": 26.43, "sem_acc": 0.9205, "time": "45-60 min per 40-frame scene on an RTX 4080"}

# Bench settings per preset (ours: tuned for the 5-minute CPU budget; see README).
SETTINGS = {
    "nuscenes-like": {"mesh_preset": "nuscenes", "render_scale": 0.25},
    "kitti-like": {"mesh_preset": "kitti", "render_scale": 0.25},
}


def renderer_throughput(mesh, seq, device: str, scale: float = 0.5, views: int = 6) -> float:
    """Full-view render_view pixels per second (no grad), averaged over a few views."""
    from pavemap.geometry import HeightField
    from pavemap.mesh.model import RoadMesh

    s = mesh.surface
    m = RoadMesh(HeightField(s.x0, s.y0, s.res, s.heights.to(device), s.valid.to(device)), mesh.rgb.to(device),
                 mesh.sem_logits.to(device), mesh.class_ids, mesh.has_semantics)
    vs = [v for f in seq.frames[::max(1, len(seq.frames) // views)] for v in f.views.values()][:views]
    render_view(m, seq.cameras[vs[0].camera], vs[0].T_world_cam, scale=scale)  # warm-up
    if device.startswith("cuda"):
        torch.cuda.synchronize()
    t, px = time.perf_counter(), 0
    for v in vs:
        out = render_view(m, seq.cameras[v.camera], v.T_world_cam, scale=scale)
        px += out["valid"].numel()
    if device.startswith("cuda"):
        torch.cuda.synchronize()
    return px / (time.perf_counter() - t)


def bench_drive(data: Path, preset: str, depth: str, device: str) -> Path:
    """The drive's folder: synthesized with sparse depth once (``PRESET-sparse``); ``PRESET-none`` is the same
    drive without its depth layer (sequence.json rewritten, images / labels / truth linked)."""
    src = data / f"{preset}-sparse"
    if not (src / "sequence.json").is_file():
        from pavemap.synth import synthesize

        t = time.perf_counter()
        synthesize(src, preset, seed=0, depth="sparse", device=device, progress=False)
        print(f"{preset}: synthesized in {time.perf_counter() - t:.0f} s", flush=True)
    if depth == "sparse":
        return src
    return no_depth_copy(src, data / f"{preset}-none")


def truth_camera_height(seq, camera: str | None = None) -> float | None:  # noqa: ANN001
    """Mean camera centre of a frame (or the ``camera``'s centre) above the true surface, median over frames
    (None without truth)."""
    import numpy as np

    from pavemap.io.truth import has_truth_height, read_truth_height

    if not has_truth_height(seq.root):
        return None
    t = read_truth_height(seq.root)
    c = np.array([np.mean([v.T_world_cam[:3, 3] for k, v in f.views.items() if camera in (None, k)], axis=0)
                  for f in seq.frames if camera is None or camera in f.views])
    z, inside = t.height_at(torch.from_numpy(c[:, :2]).double())
    return float(np.median(c[inside.numpy(), 2] - z.numpy()[inside.numpy()])) if inside.any() else None


def height_bias(out: Path | None, mesh, seq) -> dict:  # noqa: ANN001
    """Mean signed height error (m) of the mesh vs the truth over all kept and over observed vertices."""
    from pavemap.io.truth import has_truth_height, read_truth_height

    if not has_truth_height(seq.root):
        return {}
    s, t = mesh.surface, read_truth_height(seq.root)
    res = {}
    for name, mask in (("all", s.valid), ("observed", s.valid & mesh.observed if mesh.observed is not None else None)):
        if mask is None:
            continue
        xy = s.grid_xy()[mask].double().cpu()
        z, inside = t.height_at(xy)
        err = s.heights[mask].double().cpu()[inside] - z[inside]
        res[f"height_bias_{name}_m"] = round(float(err.mean()), 4) if err.numel() else None
        res[f"height_rmse_{name}_m"] = round(float((err ** 2).mean().sqrt()), 4) if err.numel() else None
    return res


def run_preset(preset: str, data: Path, device: str, out_root: Path | None, epochs: int | None,
               depth: str = "none") -> dict:
    seq_dir = bench_drive(data, preset, depth, device)
    seq = read_sequence(seq_dir)
    st = SETTINGS[preset]
    cfg = MeshConfig.preset(st["mesh_preset"])
    cfg.render_scale = st["render_scale"]
    cfg.eval_scale = 0.25
    cfg.device = device
    cfg.resume = False
    cfg.threads = 1 if device == "cpu" else None  # one thread measured faster on the shared 2-core box
    if epochs is not None:
        cfg.epochs = epochs
    out = None if out_root is None else out_root / f"mesh-{preset}-{device}-{depth}"
    t = time.perf_counter()
    mesh, m = reconstruct(seq, out, cfg, progress=True)
    total = time.perf_counter() - t
    pps = renderer_throughput(mesh, seq, device)
    hist = m["history"]
    res = {
        "frames": len(seq.frames), "views": sum(len(f.views) for f in seq.frames),
        "image": [next(iter(seq.cameras.values())).width, next(iter(seq.cameras.values())).height],
        "render_scale": cfg.render_scale, "eval_scale": cfg.eval_scale, "epochs": cfg.epochs,
        "pixels_per_step": cfg.pixels_per_step, "steps_per_epoch": m["steps_per_epoch"],
        "vertices": m["vertices"], "faces": m["faces"],
        "seconds_total": round(total, 1),
        "seconds_per_epoch": round(sum(h["seconds"] for h in hist) / max(1, len(hist)), 2),
        "peak_rss_mb": round(peak_rss_mb(), 0),
        "psnr_db": m["psnr"], "sem_acc": m["sem_acc"], "height_rmse_m": m.get("height_rmse"),
        "height_rmse_seen_m": m.get("height_rmse_seen"), "seen_vertices": m.get("height_rmse_seen_vertices"),
        "renderer_pixels_per_s": round(pps, 0), "depth": depth,
        "camera_height_true_m": truth_camera_height(seq), "camera_height_used_m": m["camera_height_init"],
        **height_bias(out, mesh, seq), "geometry": m.get("geometry"),
        "history": [{k: (round(v, 4) if isinstance(v, float) else v) for k, v in h.items()} for h in hist],
        "warnings": m["warnings"],
    }
    if device.startswith("cuda"):
        res["gpu"] = torch.cuda.get_device_name(0)
        res["peak_gpu_mem_mb"] = round(torch.cuda.max_memory_allocated() / 2**20, 0)
    print(json.dumps({k: v for k, v in res.items() if k != "history"}, indent=1), flush=True)
    return res


def main() -> None:
    ap = bench_parser(__doc__, "nuscenes-like,kitti-like", RESULTS)
    ap.add_argument("--out", type=Path, default=None, help="where to write mesh outputs (default: none)")
    ap.add_argument("--depth", choices=("none", "sparse"), default="none",
                    help="none (default, the monocular case) or the drive's sparse depth")
    a = ap.parse_args()
    results = json.loads(a.results.read_text()) if a.results.is_file() else {}
    results.setdefault("targets", TARGETS)
    results.setdefault("paper", PAPER)
    key = ("cuda" if a.device.startswith("cuda") else "cpu") + ("-sparse" if a.depth == "sparse" else "")
    entry = results.get(key) if isinstance(results.get(key), dict) and "presets" in results[key] else {}
    # rows of an older run without a depth mode are dropped, not mixed
    entry = {**entry, **machine_entry(), "commit": git_commit(),
             "presets": {k: v for k, v in entry.get("presets", {}).items() if v.get("depth") == a.depth}}
    for preset in a.presets.split(","):
        entry["presets"][preset] = run_preset(preset, a.data, a.device, a.out, a.epochs, a.depth)
        entry["presets"][preset]["load_avg"] = os.getloadavg()
        results[key] = entry
        write_results(a.results, results)
    write_results(a.results, results)


if __name__ == "__main__":
    main()
