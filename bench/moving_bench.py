"""A vehicle overtaking in stage 1: ``python bench/moving_bench.py`` → ``bench/results/moving.json``.

A vehicle overtaking on the left is painted into 12 consecutive frames of the kitti-like bench drive (no depth):
a dark box with light stripes that starts large at the left edge and pulls away towards the vanishing point.
Its pixels keep the road label, as from a segmenter that missed it or the corridor fallback. Stage 1 runs on
the clean and the painted drive with the rejection off and the settings given. Measured:

- ``vehicle_cells``: BEV cells where the painted drive's texture differs from the clean one's by more than 0.04
  with the cutoff off (the vehicle painted onto the road);
- per setting (``CUTOFF:BLOB``: ``mesh.moving_cutoff`` and ``mesh.moving_blob_px``), the texture's mean
  difference painted − clean in those cells, how many still differ by > 0.04, and the difference elsewhere;
  the held-out PSNR, the height RMSE over observed vertices and the share of training pixels left out, on
  both drives (on the clean drive every pixel left out is a false rejection).

And where the final-texture check (``mesh.texture_check``, on by default) says the texture may hold a vehicle:
the share of the vehicle cells it marks, how many marked cells lie more than 3 cells off the imprint, and what
it marks on the clean drive (every mark there is false).

Drives from ``mesh_bench`` (PAVEMAP_BENCH_DATA, default /tmp/pavemap-bench). Run it alone, niced.
"""

from __future__ import annotations

import json
import os
import shutil
import sys
import time
from pathlib import Path

import numpy as np
from PIL import Image

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import machine_entry, write_results  # noqa: E402
from mesh_bench import bench_drive  # noqa: E402
from pavemap.io.sequence import read_sequence  # noqa: E402
from pavemap.mesh import MeshConfig, reconstruct  # noqa: E402

OUT = Path(__file__).resolve().parent / "results" / "moving.json"
FIRST, COUNT = 30, 12


def vehicle_box(j: int, W: int, H: int) -> tuple[int, int, int, int]:
    """(x0, x1, y0, y1) of the vehicle in the j-th painted frame: large at the left edge, then pulling away."""
    t = j / (COUNT - 1)
    return int(0.2 * t * W), int((0.45 - 0.05 * t) * W), int(0.30 * H), int((0.95 - 0.35 * t) * H)


def painted_drive(src: Path, dst: Path) -> Path:
    """A copy of ``src`` (images linked) whose frames FIRST.. FIRST+COUNT-1 show the overtaking vehicle."""
    marker = dst / ".pavemap-moving-bench"
    if dst.exists():
        if not marker.is_file():  # never delete a folder this benchmark did not write
            raise SystemExit(f"{dst} exists and was not written by moving_bench.py; move it away or set "
                             "PAVEMAP_BENCH_DATA")
        shutil.rmtree(dst)
    dst.mkdir(parents=True)
    marker.write_text("written by bench/moving_bench.py\n")
    shutil.copy(src / "sequence.json", dst / "sequence.json")
    for name in ("semantics", "truth"):
        if (src / name).exists():
            os.symlink((src / name).resolve(), dst / name)
    seq = read_sequence(src)
    for f in seq.frames:
        for v in f.views.values():
            out = dst / v.image
            out.parent.mkdir(parents=True, exist_ok=True)
            j = f.index - seq.frames[0].index - FIRST
            if 0 <= j < COUNT:
                a = np.asarray(Image.open(src / v.image).convert("RGB")).copy()
                H, W = a.shape[:2]
                x0, x1, y0, y1 = vehicle_box(j, W, H)
                body = np.array([30, 40, 90], np.uint8)
                a[y0:y1, x0:x1] = body
                rows = np.arange(y0, y1)
                a[rows[(rows - y0) % 12 < 3], x0:x1] = 200  # stripes: texture a matcher could take for road
                Image.fromarray(a).save(out)
            else:
                os.symlink((src / v.image).resolve(), out)
    return dst


def stage_one(seq_dir: Path, out: Path, cutoff: float, blob: int) -> dict:
    cfg = MeshConfig.preset("kitti")
    cfg.render_scale, cfg.eval_scale, cfg.resume, cfg.threads = 0.25, 0.25, False, 1  # as mesh_bench
    cfg.moving_cutoff, cfg.moving_blob_px = cutoff, blob
    t = time.perf_counter()
    _, m = reconstruct(read_sequence(seq_dir), out, cfg, progress=False)
    return {"seconds": round(time.perf_counter() - t, 1), "psnr_db": m["psnr"],
            "height_rmse_seen_m": m.get("height_rmse_seen"), "moving_pixel_share": m.get("moving_pixel_share"),
            "texture_check": {k: v for k, v in (m.get("texture_check") or {}).items() if k != "patches"},
            "texture_check_top_patch": ((m.get("texture_check") or {}).get("patches") or [None])[0],
            "warnings": [w for w in m["warnings"] if "disagree" in w]}


def _grown(mask: np.ndarray, cells: int = 3) -> np.ndarray:
    """``mask`` dilated by ``cells`` (a flag just beside the imprint is on the vehicle's edge, not elsewhere)."""
    from scipy import ndimage

    return ndimage.binary_dilation(mask, iterations=cells)


def main() -> None:
    """``python bench/moving_bench.py [CUTOFF:BLOB ...]`` (default 0.15:0 0.25:0 0.15:2 0.25:2 0.1:2)."""
    settings = [(float(a), int(b)) for a, b in (x.split(":") for x in sys.argv[1:])] or [
        (0.15, 0), (0.25, 0), (0.15, 2), (0.25, 2), (0.1, 2)]
    data = Path(os.environ.get("PAVEMAP_BENCH_DATA", "/tmp/pavemap-bench"))
    clean = bench_drive(data, "kitti-like", "none", "cpu")
    painted = painted_drive(clean, data / "moving-kitti-like-none")
    work = data / "moving-runs"
    runs, bev, flagged = {}, {}, {}
    keys = ["off", *(f"{c:g}:{b}" for c, b in settings)]
    for name, seq_dir in (("clean", clean), ("painted", painted)):
        for key, (c, b) in zip(keys, [(0.0, 0), *settings], strict=True):
            runs[f"{name} {key}"] = stage_one(seq_dir, work / f"{name}-{c:g}-{b}", c, b)
            # the BEV texture as stored (uint8), on a 0-1 scale
            bev[f"{name} {key}"] = np.load(work / f"{name}-{c:g}-{b}" / "bev_rgb.npy").astype(np.float64) / 255.0
            flagged[f"{name} {key}"] = np.load(work / f"{name}-{c:g}-{b}" / "bev_contested.npy")
            print(name, key, json.dumps(runs[f"{name} {key}"]), flush=True)
    cells = np.abs(bev["painted off"] - bev["clean off"]).mean(-1) > 0.04
    from scipy import ndimage

    blob = ndimage.binary_opening(cells, structure=np.ones((3, 3), bool))
    res = {"vehicle_frames": [FIRST, FIRST + COUNT - 1], "vehicle_cells": int(cells.sum()), "runs": runs,
           "texture": {}}
    for key in keys:
        d = np.abs(bev[f"painted {key}"] - bev[f"clean {key}"]).mean(-1)
        res["texture"][key] = {"mean_diff_vehicle_cells": round(float(d[cells].mean()), 4),
                               "vehicle_cells_still_differing": int((d[cells] > 0.04).sum()),
                               "mean_diff_elsewhere": round(float(d[~cells].mean()), 5)}
        # where the report says the texture may hold a vehicle: how much of the imprint, and what else
        still = cells & (d > 0.04)
        f, fc = flagged[f"painted {key}"], flagged[f"clean {key}"]
        res["texture"][key]["contested"] = {
            "vehicle_cells_flagged": round(float(f[cells].mean()), 4),
            # the imprint proper: the vehicle cells opened by a 3 x 3 square (most other vehicle cells are thin
            # lines along paint and kerbs, the two runs' textures a pixel apart, not the vehicle)
            "imprint_blob_cells": int(blob.sum()), "imprint_blob_flagged": round(float(f[blob].mean()), 4),
            "vehicle_cells_within_1m_of_a_flag": round(float(_grown(f, 10)[cells].mean()), 4),
            "imprint_left_flagged": round(float(f[still].mean()), 4) if still.any() else None,
            "painted_flagged_cells": int(f.sum()), "painted_flagged_off_vehicle": int((f & ~_grown(cells)).sum()),
            "clean_flagged_cells": int(fc.sum())}
    res.update(machine_entry())
    write_results(OUT, res)
    print(json.dumps(res["texture"], indent=1))


if __name__ == "__main__":
    main()
