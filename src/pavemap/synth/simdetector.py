"""Simulated defect detector for synthetic sequences (``pavemap detect --detector sim``).

True detections come from the ground truth actually visible in each view (the per-view
instance maps written by ``pavemap synth``: unoccluded defect pixels), with configurable
misses, box jitter, class confusion and confidences. False positives are placed on off-road
objects (vehicles, walls/buildings, poles, vegetation, crack-like streaks on sidewalks) and on
shadows, so that by default ≈ 35 % of all detections lie off the road (the paper's filter rate).
With ``paint_share`` > 0 a share of all detections are boxes on lane paint (source ``paint``): the
mistake a real detector makes on lane lines (D00 boxes along the line), which fusion would confirm
because paint does not move; the stage-2 paint rule (:mod:`pavemap.detect.paint`) must drop them.

Alongside the detections it writes ``truth/detections_truth.jsonl``, aligned line by line:
``{"true", "defect_id", "offroad", "source", "cls_true", "road_fraction"}``. ``offroad`` is
measured, not assumed: a box is off-road when at most half of its pixels are road (SPEC §2).
"""

from __future__ import annotations

import json
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from PIL import Image

from pavemap.errors import PavemapError
from pavemap.io.atomic import atomic_write_text
from pavemap.io.owned import note_written
from pavemap.io.sequence import DETECTIONS_FILE, load_semantics, write_detections
from pavemap.synth.params import DECOY_ID_OFFSET
from pavemap.types import Detection, Sequence

SHADOW_BIT = 1 << 14
TRUTH_FILE = "truth/detections_truth.jsonl"

# wrong class given the true one (rows D00, D10, D20, D40): cracks confuse with cracks, potholes with patches
CONFUSION = np.array([
    [0.0, 0.6, 0.3, 0.1],
    [0.6, 0.0, 0.3, 0.1],
    [0.4, 0.3, 0.0, 0.3],
    [0.2, 0.2, 0.6, 0.0],
])
# class of a false positive by its source
FP_CLASS = {
    "streak": [0.6, 0.3, 0.1, 0.0],
    "vehicle": [0.25, 0.25, 0.2, 0.3],
    "building": [0.35, 0.35, 0.2, 0.1],
    "vegetation": [0.1, 0.1, 0.6, 0.2],
    "shadow": [0.1, 0.2, 0.3, 0.4],
    "stain": [0.2, 0.2, 0.3, 0.3],
    "paint": [0.7, 0.2, 0.05, 0.05],  # a line reads as a longitudinal crack
}


@dataclass
class SimDetectorConfig:
    """Knobs of the simulated detector."""

    miss_rate: float = 0.2  # probability that a visible defect is not detected in a view
    min_pixels: int = 12  # visible (unoccluded) instance pixels needed to be detectable
    box_jitter: float = 0.08  # std of each box edge, as a fraction of the box width / height
    confusion: float = 0.1  # probability of reporting a wrong class
    conf_true: tuple[float, float] = (5.0, 2.0)  # Beta(a, b) confidence of true detections
    conf_false: tuple[float, float] = (2.0, 3.5)  # Beta(a, b) confidence of false positives
    conf_min: float = 0.05  # confidences are mapped to [conf_min, 1]
    offroad_share: float = 0.35  # fraction of all detections that are off-road false positives
    onroad_fp_share: float = 0.05  # fraction that are on-road false positives (shadows, stains)
    source_weights: dict[str, float] = field(default_factory=lambda: {
        "vehicle": 0.3, "building": 0.25, "streak": 0.2, "vegetation": 0.15, "shadow": 0.1})
    fp_box_frac: tuple[float, float] = (0.02, 0.09)  # false-positive box width as a fraction of image width
    paint_share: float = 0.0  # fraction of all detections that are false positives on lane paint

    def validate(self) -> None:
        for name in ("miss_rate", "confusion", "offroad_share", "onroad_fp_share", "box_jitter", "paint_share"):
            v = getattr(self, name)
            if not 0.0 <= v <= 1.0:
                raise PavemapError(f"SimDetectorConfig.{name} must be in [0, 1], got {v}")
        if self.offroad_share + self.onroad_fp_share + self.paint_share >= 0.95:
            raise PavemapError("offroad_share + onroad_fp_share + paint_share must stay below 0.95")


# pixel codes of a view's compact map: bit 0 road, bit 1 shadow, bits 2-3 the off-road source class
_ROAD, _SHADOW = 1, 2
_SOURCES = {"vehicle": 1, "building": 2, "vegetation": 3}
_SOURCE_CLASS = {"vehicle": "vehicle", "building": "building", "vegetation": "terrain"}
_EXPANDED_KEEP = 8  # views whose pools stay expanded at once (false positives revisit views at random)


@dataclass
class _View:
    """One view's detection-relevant content, kept compact: a whole drive's views stay in memory while
    false positives are drawn, so the pixel pools are rebuilt from a compressed (H, W) uint8 code map on
    demand (a few views at a time) instead of held as int64 index arrays (~1.7 MB a view)."""

    frame: int
    camera: str
    W: int
    H: int
    code: bytes  # zlib of the (H, W) uint8 pixel codes
    sizes: dict[str, int]  # source -> number of pixels in its pool
    streaks: list[tuple[float, float, float, float]]
    paint: list[tuple[float, float, float, float]] = field(default_factory=list)  # boxes of paint pieces
    _expanded: tuple[dict[str, np.ndarray], np.ndarray] | None = field(default=None, repr=False)

    def expand(self, keep: list[_View]) -> tuple[dict[str, np.ndarray], np.ndarray]:
        """``(pools, road_ii)``: source -> (n,) int64 flat pixel indices, and the (H+1, W+1) integral image
        of road; ``keep`` is the caller's list of expanded views, the oldest dropped past a few."""
        if self._expanded is None:
            c = np.frombuffer(zlib.decompress(self.code), np.uint8).reshape(self.H, self.W)
            self._expanded = _pools(c)
            keep.append(self)
            while len(keep) > _EXPANDED_KEEP:
                keep.pop(0)._expanded = None
        return self._expanded


def _pools(code: np.ndarray) -> tuple[dict[str, np.ndarray], np.ndarray]:
    road = (code & _ROAD) > 0
    shadow = (code & _SHADOW) > 0
    src = (code >> 2).reshape(-1)
    pools = {name: np.flatnonzero(src == k) for name, k in _SOURCES.items()}
    pools["shadow"] = np.flatnonzero((shadow & ~road).reshape(-1))
    pools["road_shadow"] = np.flatnonzero((shadow & road).reshape(-1))
    pools["road"] = np.flatnonzero(road.reshape(-1))
    ii = np.zeros((code.shape[0] + 1, code.shape[1] + 1), np.int64)
    ii[1:, 1:] = road.cumsum(0).cumsum(1)
    return pools, ii


def _boxes_of_ids(ids: np.ndarray, W: int):
    """Per distinct non-zero id in a flat id map: (ids, counts, x1, y1, x2, y2) pixel-edge boxes."""
    nz = np.flatnonzero(ids)
    if nz.size == 0:
        e = np.zeros(0, np.int64)
        return e, e, e, e, e, e
    v = ids[nz]
    order = np.argsort(v, kind="stable")
    v, nz = v[order], nz[order]
    starts = np.concatenate([[0], np.flatnonzero(np.diff(v)) + 1])
    rows, cols = nz // W, nz % W
    counts = np.diff(np.concatenate([starts, [v.size]]))
    return (v[starts], counts, np.minimum.reduceat(cols, starts), np.minimum.reduceat(rows, starts),
            np.maximum.reduceat(cols, starts) + 1, np.maximum.reduceat(rows, starts) + 1)


def _road_fraction(ii: np.ndarray, box: tuple[float, float, float, float]) -> float:
    x1, y1, x2, y2 = (int(round(v)) for v in box)
    if x2 <= x1 or y2 <= y1:
        return 0.0
    s = ii[y2, x2] - ii[y1, x2] - ii[y2, x1] + ii[y1, x1]
    return float(s) / float((x2 - x1) * (y2 - y1))


def _load_view(seq: Sequence, frame, cam: str, names: dict[str, int], road_lut: np.ndarray, cfg):
    v = frame.views[cam]
    root = seq.root
    assert root is not None
    code_path = root / "truth" / "instances" / cam / Path(v.image).with_suffix(".png").name
    if not code_path.is_file():
        raise PavemapError(f"{code_path}: missing; the sim backend needs a synthetic sequence from `pavemap synth`")
    if v.semantics is None:
        raise PavemapError(f"frame {frame.index} camera {cam}: the sim backend needs semantic maps")
    with Image.open(code_path) as im:
        code = np.asarray(im).astype(np.int64)
    sem = load_semantics(root / v.semantics)
    H, W = sem.shape
    road = road_lut[sem]
    low = code & (SHADOW_BIT - 1)
    px = road.astype(np.uint8) * _ROAD | ((code & SHADOW_BIT) > 0).astype(np.uint8) * _SHADOW
    for src, cname in (("vehicle", "vehicle"), ("building", "building"), ("vegetation", "terrain")):
        if cname in names:
            px |= (sem == names[cname]).astype(np.uint8) * np.uint8(_SOURCES[src] << 2)
    pools, ii = _pools(px)
    sizes = {k: int(a.size) for k, a in pools.items() if k not in _SOURCES or _SOURCE_CLASS[k] in names}
    decoy = np.where(low >= DECOY_ID_OFFSET, low, 0).reshape(-1)
    _, cnt, x1, y1, x2, y2 = _boxes_of_ids(decoy, W)
    streaks = [(float(a), float(b), float(c), float(d)) for n, a, b, c, d in zip(cnt, x1, y1, x2, y2, strict=True)
               if n >= cfg.min_pixels]
    defects = np.where((low > 0) & (low < DECOY_ID_OFFSET), low, 0).reshape(-1)
    view = _View(frame.index, cam, W, H, zlib.compress(px.tobytes(), 1), sizes, streaks,
                 _paint_pieces(sem == names["lane_marking"], cfg) if cfg.paint_share > 0 and "lane_marking" in names
                 else [])
    return view, ii, _boxes_of_ids(defects, W)


def _conf(rng: np.random.Generator, ab: tuple[float, float], lo: float) -> float:
    return float(lo + (1 - lo) * rng.beta(*ab))


def _jitter(rng, box, frac: float, W: int, H: int):
    x1, y1, x2, y2 = box
    w, h = x2 - x1, y2 - y1
    x1 += rng.normal(0, frac * w)
    x2 += rng.normal(0, frac * w)
    y1 += rng.normal(0, frac * h)
    y2 += rng.normal(0, frac * h)
    x1, x2 = sorted((float(np.clip(x1, 0, W - 1)), float(np.clip(x2, 1, W))))
    y1, y2 = sorted((float(np.clip(y1, 0, H - 1)), float(np.clip(y2, 1, H))))
    return (x1, y1, max(x2, x1 + 1.0), max(y2, y1 + 1.0))


def detect_sequence(seq: Sequence, seed: int = 0, out: Path | None = None,
                    config: SimDetectorConfig | None = None, progress: bool = True) -> int:
    """Simulate detections for a synthetic sequence; write ``out`` (default SEQ/detections.jsonl); a progress
    bar on stderr for 50 views or more when ``progress``.

    Also writes ``truth/detections_truth.jsonl`` aligned line by line. Returns the number of detections.
    """
    from tqdm import tqdm

    cfg = config or SimDetectorConfig()
    cfg.validate()
    if seq.root is None:
        raise PavemapError("the sim backend needs a sequence read from a folder")
    rng = np.random.default_rng([int(seed), 1234])
    names = {c.name: c.id for c in seq.classes}
    road_lut = seq.class_lut("road")
    cam_order = {c: i for i, c in enumerate(seq.cameras)}
    from pavemap.synth.generate import load_truth_defects

    cls_of = {d.id: d.cls for d in load_truth_defects(seq.root)}

    dets: list[tuple[tuple, Detection, dict]] = []
    views: list[_View] = []
    n_views = sum(len(f.views) for f in seq.frames)
    bar = tqdm(total=n_views, desc="sim detect", unit="view", disable=not progress or n_views < 50)
    for f in seq.frames:
        for cam in f.views:
            view, road_ii, (ids, cnt, x1, y1, x2, y2) = _load_view(seq, f, cam, names, road_lut, cfg)
            views.append(view)
            for k in range(ids.size):
                if cnt[k] < cfg.min_pixels or rng.random() < cfg.miss_rate:
                    continue
                if int(ids[k]) - 1 not in cls_of:
                    raise PavemapError(f"{seq.root}/truth: instance map refers to defect {int(ids[k]) - 1}, "
                                       "missing from defects.geojson")
                true_cls = cls_of[int(ids[k]) - 1]
                cls = true_cls
                if rng.random() < cfg.confusion:
                    cls = int(rng.choice(4, p=CONFUSION[true_cls]))
                box = _jitter(rng, (x1[k], y1[k], x2[k], y2[k]), cfg.box_jitter, view.W, view.H)
                rf = _road_fraction(road_ii, box)
                det = Detection(f.index, cam, box, cls, _conf(rng, cfg.conf_true, cfg.conf_min))
                dets.append(((f.index, cam_order[cam]), det, {
                    "true": True, "defect_id": int(ids[k]) - 1, "offroad": rf <= 0.5, "source": "defect",
                    "cls_true": true_cls, "road_fraction": round(rf, 3)}))
            bar.update(1)
    bar.close()

    n_tp = len(dets)
    total = n_tp / max(1e-9, 1.0 - cfg.offroad_share - cfg.onroad_fp_share - cfg.paint_share)
    n_off = int(round(cfg.offroad_share * total))
    n_on = int(round(cfg.onroad_fp_share * total))
    weight = np.array([sum(v.sizes.get(s, 0) for s in ("vehicle", "building", "vegetation", "shadow"))
                       + 400 * len(v.streaks) for v in views], float)
    if n_off and weight.sum() > 0:
        dets += _false_positives(rng, cfg, views, weight / weight.sum(), n_off, offroad=True, cam_order=cam_order)
    road_w = np.array([v.sizes["road"] for v in views], float)
    if n_on and road_w.sum() > 0:
        dets += _false_positives(rng, cfg, views, road_w / road_w.sum(), n_on, offroad=False, cam_order=cam_order)

    n_paint = int(round(cfg.paint_share * total))
    paint_w = np.array([len(v.paint) for v in views], float)
    if n_paint and paint_w.sum() > 0:
        dets += _paint_positives(rng, cfg, views, paint_w / paint_w.sum(), n_paint, cam_order)
    dets.sort(key=lambda d: (d[0], d[1].box[0], d[1].box[1]))
    out = Path(out) if out is not None else seq.root / DETECTIONS_FILE
    write_detections(out, [d[1] for d in dets])
    lines = [json.dumps(d[2]) for d in dets]
    atomic_write_text(seq.root / TRUTH_FILE, "\n".join(lines) + ("\n" if lines else ""))
    note_written(seq.root / TRUTH_FILE)
    return len(dets)


def _false_positives(rng, cfg: SimDetectorConfig, views: list[_View], p_view: np.ndarray, n: int, offroad: bool,
                     cam_order: dict[str, int]):
    out: list = []
    expanded: list[_View] = []
    attempts = 0
    while len(out) < n and attempts < 20 * n + 50:
        attempts += 1
        v = views[int(rng.choice(len(views), p=p_view))]
        if offroad:
            srcs = [s for s, w in cfg.source_weights.items() if w > 0 and (
                len(v.streaks) if s == "streak" else v.sizes.get(s, 0))]
            if not srcs:
                continue
            w = np.array([cfg.source_weights[s] for s in srcs])
            src = srcs[int(rng.choice(len(srcs), p=w / w.sum()))]
        else:
            src = "shadow" if v.sizes["road_shadow"] and rng.random() < 0.6 else "stain"
        if src == "streak":
            box = _jitter(rng, v.streaks[int(rng.integers(len(v.streaks)))], cfg.box_jitter, v.W, v.H)
        else:
            pool = v.expand(expanded)[0]["road_shadow" if src == "shadow" and not offroad else
                                        ("road" if src == "stain" else src)]
            pix = int(pool[int(rng.integers(len(pool)))])
            cy, cx = divmod(pix, v.W)
            bw = max(6.0, rng.uniform(*cfg.fp_box_frac) * v.W)
            bh = max(6.0, bw * rng.uniform(0.4, 1.2))
            box = (max(0.0, cx - bw / 2), max(0.0, cy - bh / 2), min(float(v.W), cx + bw / 2),
                   min(float(v.H), cy + bh / 2))
        rf = _road_fraction(v.expand(expanded)[1], box)
        if (rf <= 0.5) != offroad:
            continue  # box does not land where this kind of false positive belongs: draw again
        cls = int(rng.choice(4, p=np.asarray(FP_CLASS[src if src in FP_CLASS else "stain"])))
        det = Detection(v.frame, v.camera, box, cls, _conf(rng, cfg.conf_false, cfg.conf_min))
        out.append(((v.frame, cam_order[v.camera]), det, {
            "true": False, "defect_id": None, "offroad": offroad, "source": src, "cls_true": None,
            "road_fraction": round(rf, 3)}))
    return out


def _paint_pieces(paint: np.ndarray, cfg: SimDetectorConfig) -> list[tuple[float, float, float, float]]:
    """Boxes of lane-paint pieces in a view: each dash, and a long line cut into pieces of at most 1.5× its
    width along the image rows (a detector boxes a stretch of a line, not the whole line)."""
    from scipy import ndimage

    lab, n = ndimage.label(paint)
    out = []
    for k, sl in enumerate(ndimage.find_objects(lab), start=1):
        if sl is None:
            continue
        ys, xs = sl
        if int((lab[sl] == k).sum()) < cfg.min_pixels:
            continue
        step = max(8, int(1.5 * max(xs.stop - xs.start, 8)))
        for y0 in range(ys.start, ys.stop, step):
            y1 = min(ys.stop, y0 + step)
            cols = np.flatnonzero((lab[y0:y1, xs] == k).any(0))
            if cols.size and (y1 - y0) * cols.size >= cfg.min_pixels:
                out.append((float(xs.start + cols[0]), float(y0), float(xs.start + cols[-1] + 1), float(y1)))
    return out


def _paint_positives(rng, cfg: SimDetectorConfig, views: list[_View], p_view: np.ndarray, n: int,
                     cam_order: dict[str, int]):
    out = []
    expanded: list[_View] = []
    for _ in range(n):
        v = views[int(rng.choice(len(views), p=p_view))]
        box = _jitter(rng, v.paint[int(rng.integers(len(v.paint)))], cfg.box_jitter, v.W, v.H)
        cls = int(rng.choice(4, p=np.asarray(FP_CLASS["paint"])))
        # as confident as a true detection: to the detector it looks real
        det = Detection(v.frame, v.camera, box, cls, _conf(rng, cfg.conf_true, cfg.conf_min))
        out.append(((v.frame, cam_order[v.camera]), det, {
            "true": False, "defect_id": None, "offroad": False, "source": "paint", "cls_true": None,
            "road_fraction": round(_road_fraction(v.expand(expanded)[1], box), 3)}))
    return out


def read_detection_truth(seq_root: str | Path) -> list[dict]:
    """The side file of the last simulated detection run, one dict per detection line."""
    path = Path(seq_root) / TRUTH_FILE
    if not path.is_file():
        raise PavemapError(f"{path}: missing; run `pavemap detect SEQ --detector sim` first")
    return [json.loads(x) for x in path.read_text(encoding="utf-8").splitlines() if x.strip()]
