"""Ablations (paper Tables 6-8) on a synthetic nuscenes-like drive, with ground-truth scores.

Rows: tau_road in {0.3, 0.5, 0.7} (Table 6), tau_conf in {0.05 ... 0.25} (Table 7), alpha in
{0.3, 0.5, 0.7, 0.9} (Table 8), n_min in {1, 2, 3}, hit radius, and association mode x mask
source (mesh / both masks only when stage 1 runs). Every row: the paper's statistics and the
ground-truth precision / recall / F1 / localisation error, with the rest at the defaults.

    .venv/bin/python bench/ablations.py            # -> bench/results/ablations.json
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))

from fusion_bench import PRESETS, configs, run_row, scene, try_mesh  # noqa: E402
from pavemap.io.atomic import atomic_write_json  # noqa: E402
from pavemap.io.sequence import read_detections, read_sequence  # noqa: E402
from pavemap.io.truth import read_truth_height  # noqa: E402

SWEEPS = {
    "tau_road": [0.3, 0.5, 0.7],
    "tau_conf": [0.05, 0.10, 0.15, 0.20, 0.25],
    "alpha": [0.3, 0.5, 0.7, 0.9],
    "n_min": [1, 2, 3],
    "hit_radius_m": [0.3, 0.5, 0.7],
}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--preset", default="nuscenes-like", choices=list(PRESETS))
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--work", type=Path, default=Path("/tmp/pavemap-bench"))
    ap.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "ablations.json")
    ap.add_argument("--no-mesh", action="store_true")
    ap.add_argument("--mesh-epochs", type=int, default=2)
    args = ap.parse_args(argv)
    fpreset, scale = PRESETS[args.preset]
    root = scene(args.work, args.preset, args.frames, scale)
    seq = read_sequence(root)
    dets = read_detections(root / "detections.jsonl")
    surface = read_truth_height(root)
    base_filter, base = configs(fpreset)
    out: dict = {"scene": root.name, "surface": "truth", "sweeps": {},
                 "defaults": {**dataclasses.asdict(base_filter), **dataclasses.asdict(base)}}
    for name, values in SWEEPS.items():
        rows = []
        for v in values:
            filt, cfg = configs(fpreset, **{name: v})
            row = run_row(seq, dets, surface, cfg, root, filt=filt)
            row[name] = v
            rows.append(row)
            print(f"[ablation] {name}={v}: F1 {row['truth']['f1']:.3f} FR {row['paper']['filter_rate']:.3f} "
                  f"MSR {row['paper']['msr']:.3f} cov {row['paper']['coverage']:.5f}", flush=True)
        out["sweeps"][name] = rows
    mesh, note = (None, "skipped (--no-mesh)") if args.no_mesh else try_mesh(seq, root, args.work, args.mesh_epochs)
    out["mesh"] = note
    rows = []
    for assoc in ("ray", "hit", "footprint"):
        for mask in ("frame", "mesh", "both"):
            if mask != "frame" and mesh is None:
                continue
            filt, cfg = configs(fpreset, association=assoc, mask=mask)
            surf = mesh.surface if mesh is not None else surface
            row = run_row(seq, dets, surf, cfg, root, mesh=mesh, filt=filt)
            row["surface"] = "mesh" if mesh is not None else "truth"
            rows.append(row)
            print(f"[ablation] {assoc}/{mask}: F1 {row['truth']['f1']:.3f} MSR {row['paper']['msr']:.3f}", flush=True)
    out["sweeps"]["association_x_mask"] = rows
    atomic_write_json(args.out, out)
    print(f"[ablation] -> {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
