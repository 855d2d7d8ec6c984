"""How COLMAP's steps take the road's scale: each step's own road reading, or the median road-to-COLMAP ratio of
the measured steps around it (``pavemap.sfm.steps.relength_path``: ``window``, ``max_dev``), judged on the
synthetic 2 Hz drives with a known path (``sfm_drives_bench``), on the KITTI sample with its true poses, and on
nuScenes clip 1 (no truth: the camera heights its own checks read) ->
``results/sfm_ratio_window.json``. ``python bench/sfm_ratio_window.py``; a quarter of an hour of CPU.
"""

from __future__ import annotations

import functools
import json
import os
import sys
import tempfile
import time
from pathlib import Path

from common import git_commit  # bench/ is the script's folder

OUT = Path(__file__).resolve().parent / "results" / "sfm_ratio_window.json"
# (window, max_dev): 0 = each step's own reading (before 5738d5c); (3, 0.2) = the default
SETTINGS = [(0, float("inf")), (3, float("inf")), (3, 0.1), (3, 0.2)]


def _with(window: int, max_dev: float) -> None:
    """The default ``relength_path`` replaced by one with these settings (the planar motion's window=0 stays)."""
    import pavemap.sfm.steps as steps

    original = getattr(steps.relength_path, "func", steps.relength_path)  # a partial set here before: its function
    steps.relength_path = functools.partial(original, window=window, max_dev=max_dev)


def main() -> None:
    import numpy as np

    import sfm_bench
    import sfm_drives_bench as drives
    from pavemap.synth.trajectory import turn_path

    out: dict = {"what": __doc__.split("\n")[0], "commit": git_commit(), "date": time.strftime("%Y-%m-%d"),
                 "load_1min": round(os.getloadavg()[0], 2), "settings": {}}
    key = {s: f"window {s[0]}, max_dev {s[1]}" for s in SETTINGS}
    for s in SETTINGS:
        out["settings"][key[s]] = {"drives": {}}
    paths = {"turn_90deg": turn_path(), "stop_and_go": drives.stop_and_go_path(), "straight": drives.straight_path()}
    with tempfile.TemporaryDirectory(prefix="pavemap-ratio-window-") as tmp:
        for preset in ("kitti-like", "nuscenes-like"):
            for name, path in paths.items():
                truth = drives.render(Path(tmp) / f"{preset}-{name}", preset, path)
                for s in SETTINGS:
                    _with(*s)
                    r = drives.run_drive(truth, "auto")
                    out["settings"][key[s]]["drives"][f"{preset}/{name}"] = {
                        k: r.get(k) for k in ("kept", "method_used", "rmse_similarity_pct", "rmse_rigid_pct",
                                              "scale_error", "refused")}
                    print(key[s], preset, name, json.dumps(r), flush=True)
    for s in SETTINGS:
        _with(*s)
        row = out["settings"][key[s]]
        d = list(row["drives"].values())
        row["drives_mean_similarity_pct"] = round(float(np.mean([x["rmse_similarity_pct"] for x in d])), 3)
        row["drives_mean_rigid_pct"] = round(float(np.mean([x["rmse_rigid_pct"] for x in d])), 3)
        k = sfm_bench.kitti()
        row["kitti"] = {x: k[x] for x in ("rmse_share", "camera_height_m", "scale_to_truth")}
        c = sfm_bench.nuscenes("nuscenes-front-clip")
        row["nuscenes_clip1"] = {"camera_height_range_m": c["camera_height_range_m"],
                                 "heights_measured": c["checks"].get("heights_measured"),
                                 "camera_height_by_dense_points_m": c["camera_height_by_dense_points_m"],
                                 "max_accel_mps2": c["speed_check"]["max_accel_mps2"], "steps_m": c["steps_m"]}
        print(key[s], json.dumps({x: row[x] for x in row if x != "drives"}), flush=True)
    OUT.parent.mkdir(parents=True, exist_ok=True)
    OUT.write_text(json.dumps(out, indent=1) + "\n")
    print(f"wrote {OUT}", file=sys.stderr)


if __name__ == "__main__":
    main()
