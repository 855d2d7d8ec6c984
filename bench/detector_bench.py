"""Detector benchmark: mAP per dataset and class, false boxes on background frames, CPU ms per frame.

For each weights file (``--weights NAME=PATH ...``), on the **original** RDD2022 photos in
``../shared/data`` (not the downscaled training copies):

- ``czech_val``: the Czech car-mounted ``val.txt`` split (ids 2500–2999, 186 photos, 42 background);
- ``china_val``: the China_MotorBike ``images/val`` split (396 photos);

ultralytics' validator (conf 0.001, the standard mAP protocol) gives mAP50, mAP50-95, precision and
recall overall and mAP50 per class. False boxes per background frame: the Czech val frames without
boxes, predicted at each ``--tau`` (the run's ``filter.tau_conf`` decides what survives).
Speed: median ms per frame of ``predict`` on 20 Czech photos, batch 1, at each ``--imgsz``, on this CPU
with torch's threads as they are. Writes ``bench/results/detector.json``.

``--parts thresholds`` (instead of the default ``map``): the operating point of each weights file at each
``--imgsz`` (precision, recall, F1 and background boxes against tau 0.05..0.60, ``detector_thresholds.py``),
added to the existing ``detector.json`` under ``operating_point_imgsz<SZ>`` (other keys kept).
``--parts clips``: ``pavemap run`` on the shared nuScenes clips at the run's default threshold and at each ``--tau``
(``detector_clips.py``), under ``real_clip_runs``.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import git_commit, machine_entry, write_results  # noqa: E402

CLASSES = ("D00", "D10", "D20", "D40")


def _val(model, data_yaml: Path, imgsz: int) -> dict:
    m = model.val(data=str(data_yaml), imgsz=imgsz, batch=8, conf=0.001, device="cpu", plots=False,
                  verbose=False, workers=0, project=tempfile.mkdtemp(prefix="pavemap-val-"))
    names = model.names
    per_class = {names[int(c)]: round(float(m.box.ap50[i]), 4) for i, c in enumerate(m.box.ap_class_index)}
    return {"mAP50": round(float(m.box.map50), 4), "mAP50_95": round(float(m.box.map), 4),
            "precision": round(float(m.box.mp), 4), "recall": round(float(m.box.mr), 4),
            "mAP50_per_class": per_class, "images": int(getattr(m, "seen", 0) or 0) or None}


def _background_frames(czech: Path) -> list[Path]:
    rels = [ln.strip() for ln in (czech / "val.txt").read_text().splitlines() if ln.strip()]
    out = []
    for r in rels:
        img = (czech / r).resolve()
        lab = czech / "labels" / f"{img.stem}.txt"
        if not lab.is_file() or not lab.read_text().strip():
            out.append(img)
    return out


def _false_boxes(model, frames: list[Path], imgsz: int, taus: list[float]) -> dict:
    confs: list[list[float]] = []
    for f in frames:
        r = model.predict(str(f), imgsz=imgsz, conf=min(taus), device="cpu", verbose=False)[0]
        confs.append([float(c) for c in r.boxes.conf.tolist()] if r.boxes is not None else [])
    return {f"{t:.2f}": {"boxes_per_frame": round(sum(sum(c >= t for c in cs) for cs in confs) / len(frames), 3),
                         "frames_with_a_box": sum(any(c >= t for c in cs) for cs in confs)}
            for t in taus} | {"frames": len(frames)}


def _speed(model, frames: list[Path], imgsz: int) -> dict:
    import numpy as np
    from PIL import Image

    imgs = [np.ascontiguousarray(np.asarray(Image.open(f).convert("RGB"))[:, :, ::-1]) for f in frames]
    model.predict(imgs[0], imgsz=imgsz, device="cpu", verbose=False)  # warm-up
    ms = []
    for im in imgs:
        t = time.perf_counter()
        model.predict(im, imgsz=imgsz, device="cpu", verbose=False)
        ms.append((time.perf_counter() - t) * 1000)
    return {"median_ms": round(statistics.median(ms), 1), "min_ms": round(min(ms), 1), "max_ms": round(max(ms), 1),
            "frames": len(ms), "image": f"{Image.open(frames[0]).size[0]}x{Image.open(frames[0]).size[1]}"}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--weights", nargs="+", default=[], help="NAME=PATH of each detector (map, thresholds)")
    ap.add_argument("--data", type=Path, default=Path(__file__).resolve().parents[2] / "shared" / "data")
    ap.add_argument("--imgsz", type=int, nargs="+", default=[640])
    ap.add_argument("--tau", type=float, nargs="+", default=[0.05, 0.10, 0.25, 0.40])
    ap.add_argument("--results", type=Path, default=Path(__file__).parent / "results" / "detector.json")
    ap.add_argument("--note", default="")
    ap.add_argument("--merge", action="store_true",
                    help="map: add the models (with --note as their 'about') to the existing results file, "
                         "keeping its other models and parts, instead of writing a new file")
    ap.add_argument("--parts", choices=("map", "thresholds", "clips"), default="map")
    ap.add_argument("--work", type=Path, default=Path(tempfile.gettempdir()) / "pavemap-bench" / "real",
                    help="clips: where the clips are imported once and run (refine_bench.py's --data/real: shared)")
    ap.add_argument("--figure", type=Path, default=None,
                    help="thresholds: PNG of the Czech val operating point (first weights, first imgsz)")
    ap.add_argument("--pred-cache", type=Path, default=None,
                    help="thresholds: npz of the predictions, written once and reused for the same weights and imgsz")
    a = ap.parse_args()
    if a.parts != "clips" and not a.weights:
        ap.error("--weights NAME=PATH is needed for the map and thresholds parts")
    if a.parts == "thresholds":
        _thresholds(a)
        return
    if a.parts == "clips":
        _clips(a)
        return

    from pavemap.detect.yolo import _import_ultralytics, load_detector, resolve_data_yaml

    _import_ultralytics()
    work = Path(tempfile.mkdtemp(prefix="pavemap-detbench-"))
    yamls = {"czech_val": resolve_data_yaml(a.data / "rdd2022-czech" / "data.yaml", work / "cz"),
             "china_val": resolve_data_yaml(a.data / "rdd2022-china-motorbike" / "data.yaml", work / "cn")}
    bg = _background_frames(a.data / "rdd2022-czech")
    speed_frames = sorted((a.data / "rdd2022-czech" / "images").glob("*.jpg"))[:20]
    res = {"commit": git_commit(), "load_avg_1m": round(os.getloadavg()[0], 2), **machine_entry(),
           "torch_threads": __import__("torch").get_num_threads(), "note": a.note, "models": {}}
    for spec in a.weights:
        name, path = spec.split("=", 1)
        model = load_detector(path)
        entry: dict = {"weights": path, "by_imgsz": {}}
        for sz in a.imgsz:
            row = {ds: _val(model, y, sz) for ds, y in yamls.items()}
            row["czech_background"] = _false_boxes(model, bg, sz, a.tau)
            row["cpu_speed"] = _speed(model, speed_frames, sz)
            entry["by_imgsz"][str(sz)] = row
            print(name, sz, {k: v.get("mAP50") for k, v in row.items() if isinstance(v, dict)},
                  row["czech_background"], row["cpu_speed"]["median_ms"], flush=True)
        res["models"][name] = entry
    res["load_avg_1m_end"] = round(os.getloadavg()[0], 2)
    if a.merge and a.results.is_file():
        res = _merged(a.results, res)
    write_results(a.results, res)


def _merged(path: Path, new: dict) -> dict:
    """The results file at ``path`` with ``new``'s models added (each with the run's commit and the note as its
    ``about``) and ``new``'s run appended to ``runs``; every other key of the file kept."""
    import json

    old = json.loads(path.read_text())
    run = {k: new[k] for k in ("commit", "load_avg_1m", "machine", "date", "torch_threads", "note",
                               "load_avg_1m_end") if k in new}
    old.setdefault("runs", []).append(run)
    for name, entry in new["models"].items():
        old.setdefault("models", {})[name] = {**entry, "about": new.get("note", ""), "commit": new["commit"]}
    return old


def _thresholds(a: argparse.Namespace) -> None:
    """The ``thresholds`` part: merge ``operating_point_imgsz<SZ>`` into the existing results file."""
    import json

    from detector_thresholds import operating_point, plot_operating_point
    from pavemap.detect.yolo import _import_ultralytics, load_detector

    _import_ultralytics()
    taus = [round(0.05 * k, 2) for k in range(1, 13)]
    res = json.loads(a.results.read_text()) if a.results.is_file() else {}
    for spec in a.weights:
        name, path = spec.split("=", 1)
        model = load_detector(path)
        for sz in a.imgsz:
            run = {"commit": git_commit(), "load_avg_1m": round(os.getloadavg()[0], 2), **machine_entry(),
                   "torch_threads": __import__("torch").get_num_threads()}
            t0 = time.perf_counter()
            op = operating_point(model, a.data, sz, taus, a.pred_cache, path)
            run |= {"load_avg_1m_end": round(os.getloadavg()[0], 2), "seconds": round(time.perf_counter() - t0)}
            res[f"operating_point_imgsz{sz}"] = {
                "what": "detector_bench.py --parts thresholds: predict once at conf 0.01 (NMS IoU 0.5, as the run), "
                        "greedy matching IoU >= 0.5 highest conf first; precision/recall/F1 and Czech background "
                        "boxes per frame at each tau (detections kept: conf >= tau)",
                "model": name, "weights": path, "imgsz": sz, "note": a.note, "run": run, **op}
            if a.figure is not None and (spec, sz) == (a.weights[0], a.imgsz[0]):
                plot_operating_point(res[f"operating_point_imgsz{sz}"], "czech_val", a.figure)
            for ds, d in op.items():
                print(name, sz, ds, {k: v for k, v in d.items() if k.startswith("best")},
                      flush=True)
    from pavemap.io.atomic import atomic_write_json

    atomic_write_json(a.results, res, indent=1)  # the file's own indent: a small diff
    print(f"-> {a.results}")


def _clips(a: argparse.Namespace) -> None:
    """The ``clips`` part: merge ``real_clip_runs`` (the run's threshold on the shared nuScenes clips) into the
    existing results file; ``--weights`` is not used (the runs use the shipped detector, as a user's would)."""
    import json

    from detector_clips import clip_runs
    from pavemap.io.atomic import atomic_write_json

    res = json.loads(a.results.read_text()) if a.results.is_file() else {}
    run = {"commit": git_commit(), "load_avg_1m": round(os.getloadavg()[0], 2), **machine_entry()}
    t0 = time.perf_counter()
    clips = clip_runs(a.data, a.work, [t for t in a.tau if t != 0])
    run |= {"load_avg_1m_end": round(os.getloadavg()[0], 2), "seconds": round(time.perf_counter() - t0)}
    res["real_clip_runs"] = {"what": "detector_bench.py --parts clips: `pavemap run` on the imported shared nuScenes "
                                     "clips at the default threshold and at each --tau (no defect truth: counts)",
                             "note": a.note, "run": run, **clips}
    atomic_write_json(a.results, res, indent=1)
    print(f"-> {a.results}")


if __name__ == "__main__":
    main()
