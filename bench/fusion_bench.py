"""Fusion benchmark (issue 4): stages 2-3 on synthetic drives, scored against ground truth.

For the nuscenes-like (6 cameras) and kitti-like (1 camera) presets: synthesise a drive, run the
simulated detector at its default noise, then filter + fuse with every association mode on the
true surface (``pavemap.io.truth.read_truth_height``) and, when stage 1 runs, on the reconstructed mesh (also
with the ``mesh`` and ``both`` road masks). Each row holds the paper's statistics (SPEC §4), the
ground-truth scores (SPEC §5) and the single-frame baseline, plus the fusion time on this CPU.

    .venv/bin/python bench/fusion_bench.py                 # 40 frames, writes bench/results/fusion.json
    .venv/bin/python bench/fusion_bench.py --frames 12 --no-mesh --out /tmp/fusion.json   # quick

Scenes are cached under ``--work`` (rerunning reuses them).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import platform
import sys
import time
import traceback
from pathlib import Path

import torch

from pavemap.detect.config import PAPER_TAU_CONF, FilterConfig
from pavemap.evaluate import evaluate
from pavemap.fuse import FusionConfig
from pavemap.io.atomic import atomic_write_json
from pavemap.io.sequence import read_detections, read_sequence
from pavemap.io.truth import read_truth_height

PRESETS = {"nuscenes-like": ("nuscenes", 0.25), "kitti-like": ("kitti", 1.0)}  # fusion preset, render scale
TARGETS = {"msr_best_mode": 0.95, "f1": 0.85, "median_error_m": 0.2, "fp_removed": 0.90, "tp_lost": 0.05,
           "fusion_seconds_40x6": 10.0}
PAPER = {"nuscenes": {"filter_rate": 0.338, "on_road_precision": 0.662, "coverage": 0.0016, "obs_per_vertex": 2.48,
                      "mean_severity": 0.157, "msr": 0.278, "avg_distance_m": 0.16},
         "kitti": {"filter_rate": 0.369, "on_road_precision": 0.631, "coverage": 0.00004, "obs_per_vertex": 2.26,
                   "mean_severity": 0.158, "msr": 0.313, "avg_distance_m": 0.12}}
PAPER_KEYS = ("total_detections", "filtered_detections", "valid_detections", "mapped_detections", "filter_rate",
              "on_road_precision", "coverage", "obs_per_vertex", "mean_severity", "msr", "avg_distance_m", "instances")
EVAL_KEYS = ("precision", "recall", "f1", "median_error_m", "p90_error_m", "fp_removed", "tp_lost",
             "class_accuracy", "median_area_ratio", "visible_defects", "truth_defects")


def scene(work: Path, preset: str, frames: int, scale: float, seed: int = 0) -> Path:
    """Synthesise (once) a drive with simulated detections; returns its folder."""
    from pavemap.synth import detect_sequence, synthesize

    root = work / f"{preset}-f{frames}-s{scale}-seed{seed}"
    if not (root / "detections.jsonl").is_file():
        t = time.perf_counter()
        synthesize(root, preset=preset, seed=seed, frames=frames, scale=scale, progress=True, overwrite=True)
        detect_sequence(read_sequence(root), seed=seed)
        print(f"[bench] synthesised {root.name} in {time.perf_counter() - t:.0f} s", flush=True)
    return root


def configs(preset: str, **changes: object) -> tuple[FilterConfig, FusionConfig]:
    """The preset's filter and fusion settings, each change applied to the section that holds the field."""
    # sim detections: the paper's tau_conf for the preset, which the simulated detector is calibrated to
    filt, fus = FilterConfig(tau_conf=PAPER_TAU_CONF[preset]), FusionConfig.preset(preset)
    for name, value in changes.items():
        target = filt if name in {f.name for f in dataclasses.fields(FilterConfig)} else fus
        if not hasattr(target, name):
            raise KeyError(f"{name}: neither a filter nor a fusion setting")
        setattr(target, name, value)
    filt.validate()
    fus.validate()
    return filt, fus


def run_row(seq, dets, surface, cfg: FusionConfig, root: Path, mesh=None,  # noqa: ANN001
            filt: FilterConfig | None = None) -> dict:
    """One filter + fusion run (filter: the default one unless given): paper metrics + GT scores + baseline."""
    from pavemap.pipeline import filter_and_fuse

    filt = filt if filt is not None else FilterConfig(tau_conf=PAPER_TAU_CONF["nuscenes"])
    t = time.perf_counter()
    res = filter_and_fuse(seq, dets, surface, filt, cfg, mesh=mesh, progress=False)
    seconds = time.perf_counter() - t
    ev = evaluate(res, root)
    b = ev["baseline"]
    return {
        "association": cfg.association, "mask": res.metrics["mask"], "fusion_seconds": round(seconds, 3),
        "paper": {k: res.metrics.get(k) for k in PAPER_KEYS},
        "truth": {k: ev.get(k) for k in EVAL_KEYS},
        "per_class_f1": {c: round(v["f1"], 3) for c, v in ev["per_class"].items()},
        "baseline": {k: b.get(k) for k in ("precision", "recall", "f1", "median_error_m", "p90_error_m")},
    }


def try_mesh(seq, root: Path, work: Path, epochs: int):  # noqa: ANN001, ANN201
    """Reconstruct the stage-1 mesh (cached); None with the reason when it cannot run."""
    try:
        from pavemap.mesh import MeshConfig, load_mesh, reconstruct
    except ImportError as e:
        return None, f"pavemap.mesh unavailable: {e}"
    out = work / f"{root.name}-mesh-e{epochs}"
    try:
        if (out / "metrics.json").is_file():
            return load_mesh(out), "cached"
        cfg = MeshConfig.preset("nuscenes" if "nuscenes" in root.name else "kitti")
        cfg.epochs = epochs
        t = time.perf_counter()
        mesh, _ = reconstruct(seq, out, cfg, progress=True)
        return mesh, f"reconstructed in {time.perf_counter() - t:.0f} s ({epochs} epochs)"
    except Exception as e:  # noqa: BLE001 - a benchmark records the failure and goes on
        traceback.print_exc()
        return None, f"reconstruct failed: {type(e).__name__}: {e}"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--work", type=Path, default=Path("/tmp/pavemap-bench"))
    ap.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "fusion.json")
    ap.add_argument("--presets", nargs="+", default=list(PRESETS))
    ap.add_argument("--no-mesh", action="store_true", help="skip stage 1 (true surface only)")
    ap.add_argument("--mesh-epochs", type=int, default=2)
    args = ap.parse_args(argv)
    torch.set_num_threads(max(1, torch.get_num_threads()))
    result: dict = {"frames": args.frames, "targets": TARGETS, "paper": PAPER, "host": platform.node(),
                    "cpu_threads": torch.get_num_threads(), "python": sys.version.split()[0], "scenes": {}}
    for preset in args.presets:
        fpreset, scale = PRESETS[preset]
        root = scene(args.work, preset, args.frames, scale)
        seq = read_sequence(root)
        dets = read_detections(root / "detections.jsonl")
        truth_surface = read_truth_height(root)
        rows = []
        for assoc in ("ray", "hit", "footprint"):
            filt, cfg = configs(fpreset, association=assoc)
            row = run_row(seq, dets, truth_surface, cfg, root, filt=filt)
            row["surface"] = "truth"
            rows.append(row)
            print(f"[bench] {preset} truth {assoc}: {json.dumps(row['truth'])} msr {row['paper']['msr']:.3f} "
                  f"t {row['fusion_seconds']} s", flush=True)
        mesh_note = "skipped (--no-mesh)"
        if not args.no_mesh:
            mesh, mesh_note = try_mesh(seq, root, args.work, args.mesh_epochs)
            if mesh is not None:
                for assoc, mask in (("ray", "frame"), ("hit", "frame"), ("footprint", "frame"), ("hit", "mesh"),
                                    ("hit", "both")):
                    filt, cfg = configs(fpreset, association=assoc, mask=mask)
                    row = run_row(seq, dets, mesh.surface, cfg, root, mesh=mesh, filt=filt)
                    row["surface"] = "mesh"
                    rows.append(row)
                    print(f"[bench] {preset} mesh {assoc}/{mask}: {json.dumps(row['truth'])} "
                          f"msr {row['paper']['msr']:.3f}", flush=True)
        n_views = sum(len(f.views) for f in seq.frames)
        result["scenes"][preset] = {"scene": root.name, "views": n_views, "render_scale": scale,
                                    "detections": len(dets), "mesh": mesh_note, "rows": rows}
    atomic_write_json(args.out, result)
    print(f"[bench] -> {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
