"""Downscaled copies of the RDD2022 training data that fit a GPU run's 64 MiB carry.

The GPU machine gets only the checkout (and carried folders, 64 MiB a call), while
``../shared/data`` holds 242 MB of photos. This writes WebP copies (labels are
normalised YOLO boxes, so they stay as they are) into two folders, one per call:

- ``.devdata/cn``: RDD2022 China_MotorBike train, 512 → ``--cn-size`` px;
- ``.devdata/cz``: RDD2022 Czech train and val (``train.txt`` / ``val.txt``), 600 → ``--cz-size`` px,
  background frames (no boxes) included with empty label files.

Usage: ``python scripts/detector_gpu/prepare_data.py [--data ../shared/data] [--out .devdata]``.
Prints each folder's size; the device script (``train.sh``) builds the dataset yaml there.
"""

from __future__ import annotations

import argparse
import shutil
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from PIL import Image


def _convert(src: Path, dst: Path, size: int, quality: int) -> int:
    im = Image.open(src).convert("RGB")
    if max(im.size) > size:
        s = size / max(im.size)
        im = im.resize((round(im.width * s), round(im.height * s)), Image.BICUBIC)
    dst.parent.mkdir(parents=True, exist_ok=True)
    im.save(dst, format="WEBP", quality=quality, method=6)
    return dst.stat().st_size


def _copy_split(pairs: list[tuple[Path, Path]], out_img: Path, out_lab: Path, size: int, quality: int) -> int:
    out_img.mkdir(parents=True, exist_ok=True)
    out_lab.mkdir(parents=True, exist_ok=True)
    jobs = []
    with ThreadPoolExecutor(4) as ex:
        for img, lab in pairs:
            jobs.append(ex.submit(_convert, img, out_img / f"{img.stem}.webp", size, quality))
            dst = out_lab / f"{img.stem}.txt"
            if lab.is_file():
                shutil.copyfile(lab, dst)
            else:  # a background frame: an empty label file says "no defect here"
                dst.write_text("")
        return sum(j.result() for j in jobs)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=Path(__file__).resolve().parents[3] / "shared" / "data")
    ap.add_argument("--out", type=Path, default=Path(".devdata"))
    ap.add_argument("--cn-size", type=int, default=448)
    ap.add_argument("--cz-size", type=int, default=512)
    ap.add_argument("--quality", type=int, default=55)
    a = ap.parse_args()

    cn = a.data / "rdd2022-china-motorbike"
    pairs = [(p, cn / "labels" / "train" / f"{p.stem}.txt") for p in sorted((cn / "images" / "train").glob("*.jpg"))]
    n = _copy_split(pairs, a.out / "cn" / "images" / "train", a.out / "cn" / "labels" / "train",
                    a.cn_size, a.quality)
    print(f"cn train: {len(pairs)} images, {n / 2**20:.1f} MiB")

    cz = a.data / "rdd2022-czech"
    for split in ("train", "val"):
        rels = [ln.strip() for ln in (cz / f"{split}.txt").read_text().splitlines() if ln.strip()]
        imgs = [(cz / r).resolve() for r in rels]
        pairs = [(p, cz / "labels" / f"{p.stem}.txt") for p in imgs]
        n = _copy_split(pairs, a.out / "cz" / "images" / split, a.out / "cz" / "labels" / split,
                        a.cz_size, a.quality)
        bg = sum(1 for _, lab in pairs if not lab.is_file() or not lab.read_text().strip())
        print(f"cz {split}: {len(pairs)} images ({bg} background), {n / 2**20:.1f} MiB")


if __name__ == "__main__":
    main()
