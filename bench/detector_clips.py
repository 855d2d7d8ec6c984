"""The detector's threshold on the shared nuScenes clips (part ``clips`` of bench/detector_bench.py).

Real dashcam frames have no defect truth, so this part counts and keeps the evidence: each clip is imported once
(``pavemap import folder --poses sfm``, shared with bench/refine_real.py's ``WORK``) and run as a user would, with
the run's default threshold (the detector's operating point) and with ``--set filter.tau_conf=<each --tau>``.
Per run: the threshold and why, boxes in / at or above it / kept on the road, the defects mapped (class,
confidence, sightings, position, evidence crop) and the detector check. Look at the crops before quoting a
defect as real.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

import yaml

from refine_real import _pavemap, imported

CLIPS = ("nuscenes-clip-1", "nuscenes-clip-2")


def _one(seq: Path, out: Path, tau: float | None) -> dict:
    args = ["run", str(seq), "--out", str(out), "--overwrite"] + (["--set", f"filter.tau_conf={tau}"] if tau else [])
    log = out.parent / f"{out.name}.log"
    secs = _pavemap(args, log)
    said = next((ln for ln in log.read_text().splitlines() if ln.startswith("filter.tau_conf")), "")
    m = json.loads((out / "metrics.json").read_text())
    check = (m.get("maintenance") or {}).get("detector_confidence") or {}
    used = yaml.safe_load((out / "config.yaml").read_text())["filter"]["tau_conf"]
    with (out / "defects.csv").open(newline="") as fh:  # local metres: a clip without a geo origin has no GeoJSON
        defects = [{k: row.get(k) for k in ("code", "confidence", "observations", "x_m", "y_m", "priority",
                                            "evidence")} for row in csv.DictReader(fh)]
    return {"tau_conf": used, "why": said, "boxes": m["input_detections"], "below_conf": m["below_conf"],
            "off_road": m["filtered_detections"], "kept": m["valid_detections"], "defects": defects,
            "detector_check_low": check.get("low"), "assessed_segments": (m.get("maintenance") or {}).get(
                "assessed_segments"), "seconds": round(secs, 1), "run": str(out)}


def clip_runs(data: Path, work: Path, taus: list[float]) -> dict:
    """Per clip: the run at the default threshold (``default``) and at each of ``taus``."""
    res = {}
    (work / "runs").mkdir(parents=True, exist_ok=True)
    for name in CLIPS:
        seq = imported(data, work, name)
        runs = {"default": _one(seq, work / "runs" / f"{name}-tau-default", None)}
        for t in taus:
            runs[f"{t:g}"] = _one(seq, work / "runs" / f"{name}-tau-{t:g}", t)
        res[name] = runs
        for k, r in runs.items():
            print(name, k, r["tau_conf"], f"{r['boxes']} boxes, {r['boxes'] - r['below_conf']} >= tau, "
                  f"{len(r['defects'])} defects, check low {r['detector_check_low']}", flush=True)
    return res
