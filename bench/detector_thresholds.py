"""Operating point of a detector: precision, recall and F1 against the run's confidence threshold.

mAP is threshold-free; what a user of ``pavemap run`` sees is the set of boxes with
``conf >= filter.tau_conf``. This part predicts once at conf 0.01 (as the run does: ``detector.conf``,
NMS IoU 0.5, BGR arrays in batches of 8), then for each tau on a grid counts, per image:

- greedy matching of predicted boxes to truth boxes, highest confidence first, each truth box taken
  at most once, IoU >= 0.5; **class-aware** (same class only) and **class-agnostic** (any defect box
  on any defect: a crack called the wrong crack class is still a found defect for a road engineer);
- precision, recall, F1 overall and per class (class-aware: by the class of box and truth; agnostic:
  recall by the truth's class, precision by the predicted class);
- false boxes per background frame (the frames without a truth box; Czech val has 42).

Greedy matching highest-confidence first makes the match of a box independent of every box below it,
so one matching at conf 0.01 serves every tau >= 0.01: the boxes matched at tau are the matched boxes
with conf >= tau.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

CLASSES = ("D00", "D10", "D20", "D40")
IOU_MATCH = 0.5


@dataclass
class ImageResult:
    """One photo: predictions (conf >= the prediction floor) and truth, in original pixels.

    pred_xyxy (N, 4), pred_cls (N,) int pavemap class, pred_conf (N,); true_xyxy (M, 4), true_cls (M,).
    """

    name: str
    pred_xyxy: np.ndarray
    pred_cls: np.ndarray
    pred_conf: np.ndarray
    true_xyxy: np.ndarray
    true_cls: np.ndarray


def iou_matrix(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """IoU of every box of ``a`` (N, 4 xyxy) with every box of ``b`` (M, 4 xyxy) → (N, M)."""
    if len(a) == 0 or len(b) == 0:
        return np.zeros((len(a), len(b)))
    lt = np.maximum(a[:, None, :2], b[None, :, :2])  # (N, M, 2)
    rb = np.minimum(a[:, None, 2:], b[None, :, 2:])
    inter = np.prod(np.clip(rb - lt, 0, None), axis=2)  # (N, M)
    area_a = np.prod(np.clip(a[:, 2:] - a[:, :2], 0, None), axis=1)  # (N,)
    area_b = np.prod(np.clip(b[:, 2:] - b[:, :2], 0, None), axis=1)  # (M,)
    union = area_a[:, None] + area_b[None, :] - inter
    return np.where(union > 0, inter / np.maximum(union, 1e-12), 0.0)


def greedy_match(im: ImageResult, class_aware: bool) -> np.ndarray:
    """Truth index matched by each prediction (N,) int, -1 where none: highest confidence first, each truth
    once, the unmatched truth of highest IoU >= 0.5 (same class when ``class_aware``)."""
    iou = iou_matrix(im.pred_xyxy, im.true_xyxy)  # (N, M)
    if class_aware:
        iou = np.where(im.pred_cls[:, None] == im.true_cls[None, :], iou, -1.0)
    match = np.full(len(im.pred_conf), -1, dtype=np.int64)
    free = np.ones(len(im.true_cls), dtype=bool)
    for i in np.argsort(-im.pred_conf, kind="stable"):  # loop over boxes only; the IoU is vectorised
        if not free.any():
            break
        cand = np.where(free, iou[i], -1.0)
        j = int(np.argmax(cand))
        if cand[j] >= IOU_MATCH:
            match[i] = j
            free[j] = False
    return match


def _r4(v: float | None) -> float | None:
    return None if v is None else round(v, 4)


def _f1(p: float | None, r: float | None) -> float | None:
    """Harmonic mean; 0 when nothing was found (recall 0), None where precision or recall is undefined."""
    if r == 0.0:
        return 0.0
    if p is None or r is None:
        return None
    return _r4(2 * p * r / (p + r)) if p + r > 0 else 0.0


def _prf(tp: int, n_pred: int, n_true: int) -> dict:
    p = tp / n_pred if n_pred else None
    r = tp / n_true if n_true else None
    f1 = 2 * tp / (n_pred + n_true) if n_pred + n_true else None
    return {"precision": _r4(p), "recall": _r4(r), "f1": _r4(f1), "tp": tp, "boxes": n_pred, "truth": n_true}


def sweep(images: list[ImageResult], taus: list[float], class_aware: bool) -> dict:
    """The F1-maximising tau, and per tau (records, a table each): overall ``rows`` and ``per_class``
    precision / recall / F1 with their counts (tp, boxes kept, truth boxes)."""
    conf = np.concatenate([im.pred_conf for im in images])  # (P,) every box of every image
    pcls = np.concatenate([im.pred_cls for im in images])  # (P,)
    tcls = np.concatenate([im.true_cls for im in images])  # (T,)
    mtc = []  # per image (N,): the class of the truth each box matched, -1 = a false box
    for im in images:
        m = greedy_match(im, class_aware)
        mtc.append(im.true_cls[m] if len(im.true_cls) else m)  # m == -1 indexes the last truth: masked below
        mtc[-1] = np.where(m >= 0, mtc[-1], -1)
    mtc = np.concatenate(mtc)  # (P,)
    rows, per_class = [], []
    for t in taus:
        keep = conf >= t
        rows.append({"tau": t, **_prf(int((keep & (mtc >= 0)).sum()), int(keep.sum()), len(tcls))})
        for c, name in enumerate(CLASSES):
            n_pred_c = int((keep & (pcls == c)).sum())
            tp_pred_c = int((keep & (pcls == c) & (mtc >= 0)).sum())  # boxes of class c that found a defect
            pc = _prf(int((keep & (mtc == c)).sum()), n_pred_c, int((tcls == c).sum()))  # tp: truths of c found
            pc["precision"] = _r4(tp_pred_c / n_pred_c) if n_pred_c else None
            pc["f1"] = _f1(pc["precision"], pc["recall"])
            per_class.append({"tau": t, "class": name, **pc})
    best = max(rows, key=lambda r: (r["f1"] or 0.0, -r["tau"]))
    return {"best_tau": best["tau"], "best_f1": best["f1"], "rows": rows, "per_class": per_class}


def background_boxes(images: list[ImageResult], taus: list[float]) -> list[dict]:
    """Per tau: false boxes per background frame (the images without truth) and frames with a box."""
    bg = [im for im in images if len(im.true_cls) == 0]
    out = []
    for t in taus:
        n = [int((im.pred_conf >= t).sum()) for im in bg]
        out.append({"tau": t, "boxes_per_frame": round(sum(n) / max(len(bg), 1), 3),
                    "frames_with_a_box": sum(k > 0 for k in n), "frames": len(bg)})
    return out


def summary(aware: dict, agnostic: dict, bg: list[dict] | None) -> list[dict]:
    """One table row per tau: the class-aware and class-agnostic figures side by side, background boxes."""
    out = []
    for k, (a, g) in enumerate(zip(aware["rows"], agnostic["rows"], strict=True)):
        row = {"tau": a["tau"], "boxes": a["boxes"], "precision": a["precision"], "recall": a["recall"],
               "f1": a["f1"], "precision_agnostic": g["precision"], "recall_agnostic": g["recall"],
               "f1_agnostic": g["f1"]}
        if bg is not None:
            row["bg_boxes_per_frame"] = bg[k]["boxes_per_frame"]
        out.append(row)
    return out


def read_yolo_labels(path: Path, w: int, h: int) -> tuple[np.ndarray, np.ndarray]:
    """YOLO txt (class cx cy w h, normalised) → (M, 4) xyxy pixels and (M,) class; missing file = no box."""
    if not path.is_file():
        return np.zeros((0, 4)), np.zeros(0, dtype=np.int64)
    rows = [ln.split() for ln in path.read_text().splitlines() if ln.strip()]
    if not rows:
        return np.zeros((0, 4)), np.zeros(0, dtype=np.int64)
    a = np.array([[float(x) for x in r[:5]] for r in rows])  # (M, 5)
    cx, cy, bw, bh = a[:, 1] * w, a[:, 2] * h, a[:, 3] * w, a[:, 4] * h
    return np.stack([cx - bw / 2, cy - bh / 2, cx + bw / 2, cy + bh / 2], axis=1), a[:, 0].astype(np.int64)


def predict_images(model, paths: list[Path], label_of, imgsz: int, conf: float = 0.01,
                   batch: int = 8) -> list[ImageResult]:
    """Predict each photo as ``pavemap run`` does (BGR arrays, NMS IoU 0.5, classes mapped by name) and pair
    it with its truth (``label_of(path) -> label file``)."""
    from PIL import Image

    from pavemap.detect.classmap import build_class_map

    lut, _ = build_class_map(model.names, None)
    out: list[ImageResult] = []
    for i in range(0, len(paths), batch):
        chunk = paths[i:i + batch]
        imgs = [np.ascontiguousarray(np.asarray(Image.open(p).convert("RGB"))[:, :, ::-1]) for p in chunk]
        res = model.predict(imgs, imgsz=imgsz, conf=conf, iou=0.5, device="cpu", batch=len(imgs), verbose=False)
        for p, im, r in zip(chunk, imgs, res, strict=True):
            xyxy = r.boxes.xyxy.cpu().numpy().astype(np.float64)  # (N, 4)
            mcls = r.boxes.cls.cpu().numpy().astype(np.int64)
            ours = lut[np.clip(mcls, 0, len(lut) - 1)] if len(mcls) else mcls
            keep = ours >= 0
            tx, tc = read_yolo_labels(label_of(p), im.shape[1], im.shape[0])
            out.append(ImageResult(p.name, xyxy[keep], ours[keep], r.boxes.conf.cpu().numpy()[keep].astype(float),
                                   tx, tc))
    return out


def save_cache(path: Path, sets: dict[str, list[ImageResult]], tag: str) -> None:
    """All predictions and truth in one npz (a rerun of the sweep or the figure needs no prediction), with ``tag``
    (what predicted them: weights and input size)."""
    arrs: dict[str, np.ndarray] = {"meta/tag": np.array(tag)}
    for ds, ims in sets.items():
        for k, im in enumerate(ims):
            for f in ("pred_xyxy", "pred_cls", "pred_conf", "true_xyxy", "true_cls"):
                arrs[f"{ds}/{k:05d}/{im.name}/{f}"] = getattr(im, f)
    tmp = path.with_name(path.name + ".part.npz")
    np.savez_compressed(tmp, **arrs)
    tmp.replace(path)


def load_cache(path: Path, tag: str) -> dict[str, list[ImageResult]] | None:
    """The inverse of :func:`save_cache`; None when the file holds another weights' or input size's predictions."""
    z = np.load(path)
    if "meta/tag" not in z.files or str(z["meta/tag"]) != tag:
        print(f"{path}: predictions of another detector or input size; predicting again", flush=True)
        return None
    by: dict[str, dict[tuple[int, str], dict]] = {}
    for key in z.files:
        if key.startswith("meta/"):
            continue
        ds, k, name, f = key.split("/")
        by.setdefault(ds, {}).setdefault((int(k), name), {})[f] = z[key]
    return {ds: [ImageResult(name, **d[(k, name)]) for k, name in sorted(d)] for ds, d in by.items()}


def after_paint_rule(images: list[ImageResult], paths: dict[str, Path], tau_paint: float) -> list[ImageResult]:
    """``images`` without the boxes the run's paint rule drops (:mod:`pavemap.detect.paint`: paint from the photo
    spanning the box, cover >= ``tau_paint``), as stage 2 of ``pavemap run`` would on a view without semantics;
    ``paths`` name -> the photo."""
    from pavemap.detect.paint import box_paint_cover, paint_from_image
    from pavemap.io.sequence import load_rgb

    out = []
    for im in images:
        keep = np.ones(len(im.pred_conf), dtype=bool)
        if len(keep):
            keep = box_paint_cover(paint_from_image(load_rgb(paths[im.name])), im.pred_xyxy) < tau_paint
        out.append(ImageResult(im.name, im.pred_xyxy[keep], im.pred_cls[keep], im.pred_conf[keep], im.true_xyxy,
                               im.true_cls))
    return out


def czech_val_images(czech: Path) -> list[Path]:
    """The Czech ``val.txt`` photos (186)."""
    rels = [ln.strip() for ln in (czech / "val.txt").read_text().splitlines() if ln.strip()]
    return [(czech / r).resolve() for r in rels]


def operating_point(model, data: Path, imgsz: int, taus: list[float], cache: Path | None, weights: str) -> dict:
    """The whole part: predict (or read ``cache``, when it holds these ``weights``' predictions at ``imgsz``),
    sweep both matchings on both datasets, background boxes."""
    import hashlib

    tag = f"{hashlib.sha256(Path(weights).read_bytes()).hexdigest()}@{imgsz}"
    sets = load_cache(cache, tag) if cache is not None and cache.is_file() else None
    if sets is None:
        cz, cn = data / "rdd2022-czech", data / "rdd2022-china-motorbike"
        sets = {"czech_val": predict_images(model, czech_val_images(cz), lambda p: cz / "labels" / f"{p.stem}.txt",
                                            imgsz),
                "china_val": predict_images(model, sorted((cn / "images" / "val").glob("*.jpg")),
                                            lambda p: cn / "labels" / "val" / f"{p.stem}.txt", imgsz)}
        if cache is not None:
            save_cache(cache, sets, tag)
    from pavemap.detect.config import FilterConfig

    tau_paint = FilterConfig().tau_paint
    cz = data / "rdd2022-czech"
    sets["czech_val_after_paint_rule"] = after_paint_rule(sets["czech_val"], {p.name: p for p in czech_val_images(cz)},
                                                          tau_paint)
    out: dict = {}
    for ds, ims in sets.items():
        aware, agnostic = sweep(ims, taus, True), sweep(ims, taus, False)
        bg = background_boxes(ims, taus) if ds.startswith("czech_val") else None
        out[ds] = {"images": len(ims), "truth_boxes": aware["rows"][0]["truth"],
                   "background_frames": sum(len(im.true_cls) == 0 for im in ims)}
        for mode, sw in (("class_aware", aware), ("class_agnostic", agnostic)):
            out[ds][f"best_tau_{mode}"] = sw["best_tau"]
            out[ds][f"best_f1_{mode}"] = sw["best_f1"]
            if bg is not None:
                out[ds][f"bg_boxes_per_frame_at_best_{mode}"] = bg[taus.index(sw["best_tau"])]["boxes_per_frame"]
        out[ds]["summary"] = summary(aware, agnostic, bg)
        out[ds]["class_aware_per_class"] = aware["per_class"]
        out[ds]["class_agnostic_per_class"] = agnostic["per_class"]
        if bg is not None:
            out[ds]["background"] = bg
    out["czech_val_after_paint_rule"]["what"] = (
        f"the Czech val boxes left after the run's paint rule (filter.tau_paint {tau_paint}, paint found in the "
        "photo, as on a view without semantics)")
    return out


def plot_operating_point(op: dict, ds: str, out: Path, target_bg: float = 0.15) -> None:
    """Precision, recall, F1 (class-aware solid, agnostic dashed) and background boxes per frame against tau
    for dataset ``ds`` of an ``operating_point_imgsz*`` entry; a small PNG at ``out``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = op[ds]["summary"]
    taus = [r["tau"] for r in rows]
    fig, ax = plt.subplots(figsize=(6.4, 3.6), dpi=100)
    for key, colour in (("precision", "tab:blue"), ("recall", "tab:orange"), ("f1", "tab:green")):
        ax.plot(taus, [r[key] for r in rows], "-o", ms=3, color=colour, label=key)
        ax.plot(taus, [r[f"{key}_agnostic"] for r in rows], "--", color=colour, lw=1)
    ax.axvline(op[ds]["best_tau_class_aware"], color="tab:green", lw=0.8, ls=":")
    ax.set(xlabel="tau_conf (keep conf >= tau)", ylabel="precision / recall / F1", ylim=(0, 1))
    lines, labels = ax.get_legend_handles_labels()
    if "bg_boxes_per_frame" in rows[0]:
        ax2 = ax.twinx()
        ax2.plot(taus, [r["bg_boxes_per_frame"] for r in rows], "-s", ms=3, color="tab:red",
                 label="false boxes / background frame")
        ax2.axhline(target_bg, color="tab:red", lw=0.8, ls=":", label=f"target <= {target_bg}")
        ax2.set(ylabel="false boxes per background frame", ylim=(0, None))
        more = ax2.get_legend_handles_labels()
        lines, labels = lines + more[0], labels + more[1]
    ax.legend(lines, labels, fontsize=7, loc="upper center")
    ax.set_title(f"{ds}, imgsz {op['imgsz']} (solid: class-aware, dashed: class-agnostic; "
                 f"{op[ds]['images']} photos)", fontsize=8)
    fig.tight_layout()
    tmp = out.with_name(out.stem + ".part.png")
    fig.savefig(tmp, dpi=100)
    plt.close(fig)
    tmp.replace(out)
