"""Fine-tune pavemap's road-defect detector on a CPU, on the original RDD2022 photos (no GPU machine needed).

The GPU run (``scripts/detector_gpu``) trained on downscaled WebP copies that one device call could carry; the
original photos are a domain of their own (their JPEG compression, 600 px), so this continues from given weights
on the originals: the Czech car-mounted ``train.txt`` (its background frames included) plus a fixed random
sample of the China_MotorBike train photos, replayed so the motorbike view is not forgotten (a Czech-only CPU
fine-tune dropped China val mAP50 0.88 -> 0.45). The Czech ``val.txt`` is never trained on (it is the test), and
ultralytics' per-epoch validation is off, so nothing is chosen on it: the last epoch's weights are the result.

The dataset is a folder of links under ``--work`` (images linked, label files copied: nothing is copied into the
repository and nothing is written beside the shared data); ultralytics' wall-time budget (``--hours``) fits the
epochs and the learning-rate schedule. Run it niced beside other work; ``--resume`` continues a stopped run.

    python scripts/detector_cpu/finetune.py --init src/pavemap/weights/pavemap-yolov5n-rdd2022.pt \\
        --work /tmp/pavemap-cpu-ft --hours 2.1
    python scripts/detector_cpu/finetune.py --work /tmp/pavemap-cpu-ft --resume   # after a stop
"""

from __future__ import annotations

import argparse
import random
import sys
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[2]
NAMES = {0: "D00", 1: "D10", 2: "D20", 3: "D40"}


def _link(img: Path, labels: Path, split: Path) -> str:
    """``img`` linked into ``split``/images with its label file (empty for a background frame) in
    ``split``/labels, as ultralytics pairs them; the link's path."""
    (split / "images").mkdir(parents=True, exist_ok=True)
    (split / "labels").mkdir(parents=True, exist_ok=True)
    dst = split / "images" / img.name
    if not dst.is_symlink():
        dst.symlink_to(img)
    lab = labels / f"{img.stem}.txt"
    (split / "labels" / f"{img.stem}.txt").write_text(lab.read_text() if lab.is_file() else "")
    return str(dst)


def write_dataset(data: Path, work: Path, china: int, seed: int) -> Path:
    """The dataset yaml of the fine-tune under ``work``: Czech train + ``china`` China_MotorBike train photos
    (a fixed sample), the Czech val as ``val`` (for whoever validates by hand; training does not)."""
    cz = data / "rdd2022-czech"
    cz_train = [_link((cz / r).resolve(), cz / "labels", work / "cz") for r in (cz / "train.txt").read_text().split()]
    cz_val = [_link((cz / r).resolve(), cz / "labels", work / "czval") for r in (cz / "val.txt").read_text().split()]
    cn = data / "rdd2022-china-motorbike"
    photos = sorted((cn / "images" / "train").glob("*.jpg"))
    cn_train = [_link(p, cn / "labels" / "train", work / "cn")
                for p in random.Random(seed).sample(photos, min(china, len(photos)))]
    (work / "train.txt").write_text("".join(f"{p}\n" for p in cz_train + cn_train))
    (work / "val.txt").write_text("".join(f"{p}\n" for p in cz_val))
    out = work / "data.yaml"
    out.write_text(yaml.safe_dump({"path": str(work), "train": "train.txt", "val": "val.txt", "names": NAMES},
                                  sort_keys=False))
    print(f"{len(cz_train)} Czech + {len(cn_train)} China training photos, {len(cz_val)} Czech val -> {out}")
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--init", type=Path, default=ROOT / "src" / "pavemap" / "weights" / "pavemap-yolov5n-rdd2022.pt")
    ap.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data")
    ap.add_argument("--work", type=Path, required=True)
    ap.add_argument("--hours", type=float, default=2.1)
    ap.add_argument("--china", type=int, default=600, help="China_MotorBike photos replayed")
    ap.add_argument("--imgsz", type=int, default=640)
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--lr0", type=float, default=0.002)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--resume", action="store_true", help="continue the run under --work from its last.pt")
    a = ap.parse_args()
    sys.path.insert(0, str(ROOT / "src"))
    from pavemap.detect.yolo import train_detector

    runs = a.work / "runs"
    if a.resume:
        best = train_detector(a.work / "data.yaml", resume=runs / "cpu-ft" / "weights" / "last.pt")
    else:
        data = write_dataset(a.data, a.work, a.china, a.seed)
        best = train_detector(
            data, model=str(a.init), epochs=100, imgsz=a.imgsz, device="cpu", batch=a.batch, project=runs,
            name="cpu-ft", time_hours=a.hours, workers=a.workers, cache="ram", plots=False, seed=a.seed,
            val=False, lr0=a.lr0, lrf=0.1, optimizer="SGD", momentum=0.937, warmup_epochs=0.5, close_mosaic=1,
            patience=1000, amp=False)
    print(f"done: {best.parent / 'last.pt'} (the last epoch: the weights to evaluate)")


if __name__ == "__main__":
    main()
