"""Train pavemap's road-defect detector on a GPU machine: several runs side by side, one time budget.

Runs (``--runs``, each a child process sharing the machine's cores):
- ``coco``: YOLOv5n (ultralytics' anchor-free ``yolov5n.yaml``) from the COCO start
  (``--coco-start``, made by :func:`pavemap.detect.pretrained.coco_start_checkpoint`);
- ``shipped``: the previous default (YOLOv8n trained on China_MotorBike only,
  ``models/pavemap-yolov8n-rdd2022-cn.pt`` before 2026-12-04) fine-tuned on the same data;
- ``coco-nobg``: the COCO start without the Czech background frames.

Data: the downscaled copies of ``prepare_data.py`` under ``--data`` (``cn/`` China_MotorBike train,
``cz/`` Czech train and val). The Czech ``val`` split is the run's val set: it is watched per epoch,
but the weights kept are the **last** epoch's (``last.pt``), not the best on val, so the Czech val
scores stay a test. Copies ``last.pt``, ``results.csv`` and the log of each run to ``--out``.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import yaml

NAMES = {0: "D00", 1: "D10", 2: "D20", 3: "D40"}


def write_yaml(data: Path, work: Path, background: bool) -> Path:
    """An ultralytics dataset yaml over the copies; without ``background`` a list of the Czech frames with boxes."""
    cz_train: str | Path = data / "cz" / "images" / "train"
    if not background:
        keep = [p for p in sorted(Path(cz_train).glob("*.webp"))
                if (data / "cz" / "labels" / "train" / f"{p.stem}.txt").read_text().strip()]
        cz_train = work / "cz_train_boxes.txt"
        cz_train.write_text("".join(f"{p}\n" for p in keep))
    train = [str(cz_train)]
    if (data / "cn" / "images" / "train").is_dir():  # missing when the GPU machine was not kept between calls
        train.insert(0, str(data / "cn" / "images" / "train"))
    else:
        print("WARNING: no China_MotorBike copy under", data, "- training on the Czech data alone", flush=True)
    d = {"path": str(data), "train": train,
         "val": str(data / "cz" / "images" / "val"), "names": NAMES}
    out = work / f"rdd-{'bg' if background else 'nobg'}.yaml"
    out.write_text(yaml.safe_dump(d, sort_keys=False))
    return out


def child(a: argparse.Namespace) -> None:
    """One training run (in its own process)."""
    from pavemap.detect.yolo import train_detector

    model = {"coco": a.coco_start, "coco-nobg": a.coco_start, "shipped": a.shipped}[a.child]
    data = write_yaml(a.data, a.work, background=a.child != "coco-nobg")
    train_detector(
        data, model=str(model), epochs=a.epochs, imgsz=a.imgsz, device=a.device, batch=a.batch,
        project=a.work / "runs", name=a.child, time_hours=a.hours, workers=a.workers, cache="ram",
        plots=False, seed=0, fraction=a.fraction, close_mosaic=a.close_mosaic, patience=1000,
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, required=True)
    ap.add_argument("--work", type=Path, default=Path("/tmp/pavemap-train"))
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--coco-start", type=Path, required=True)
    ap.add_argument("--shipped", type=Path, default=Path("models/pavemap-yolov8n-rdd2022-cn.pt"))
    ap.add_argument("--runs", default="coco,shipped")
    ap.add_argument("--hours", type=float, default=None)
    ap.add_argument("--epochs", type=int, default=100)
    ap.add_argument("--imgsz", type=int, default=640)
    ap.add_argument("--batch", type=int, default=32)
    ap.add_argument("--workers", type=int, default=7)
    ap.add_argument("--device", default="auto")
    ap.add_argument("--fraction", type=float, default=1.0)
    ap.add_argument("--close-mosaic", type=int, default=10)
    ap.add_argument("--child", default=None)
    a = ap.parse_args()
    a.work.mkdir(parents=True, exist_ok=True)
    if a.child:
        child(a)
        return
    a.out.mkdir(parents=True, exist_ok=True)
    procs = {}
    t0 = time.time()
    for run in a.runs.split(","):
        log = open(a.work / f"{run}.log", "w")  # noqa: SIM115 - closed after the child ends
        cmd = [sys.executable, __file__, *sys.argv[1:], "--child", run]
        procs[run] = (subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT), log)
    summary = {}
    for run, (p, log) in procs.items():
        rc = p.wait()
        log.close()
        d = a.work / "runs" / run
        summary[run] = {"rc": rc, "wall_s": round(time.time() - t0, 1)}
        for src, dst in ((d / "weights" / "last.pt", f"{run}-last.pt"), (d / "results.csv", f"{run}-results.csv"),
                         (a.work / f"{run}.log", f"{run}.log")):
            if src.is_file():
                shutil.copyfile(src, a.out / dst)
    (a.out / "summary.json").write_text(json.dumps(summary, indent=1))
    print(json.dumps(summary))


if __name__ == "__main__":
    main()
