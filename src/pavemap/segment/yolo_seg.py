"""ultralytics semantic-segmentation backend (task ``semantic``, e.g. YOLO26-sem weights).

The model's class names are mapped to a label table by name (:class:`LabelMap.names`,
e.g. the ``mapillary-vistas`` preset maps Vistas names to RoMe's classes); names it does
not know go to the table's ``other`` class. Offline like the detector: local weights only.
"""

from __future__ import annotations

import logging
import os

import numpy as np

from pavemap.errors import PavemapError
from pavemap.segment.labels import LabelMap, _norm, load_label_map
from pavemap.types import SemanticClass

log = logging.getLogger(__name__)


class UltralyticsSegmenter:
    """Segmenter over a local ultralytics ``semantic`` model (.pt). See :class:`pavemap.segment.Segmenter`."""

    def __init__(self, weights: str | os.PathLike, class_map: str | os.PathLike | LabelMap = "mapillary-vistas",
                 imgsz: int = 640, device: str = "auto"):
        from pavemap.detect.yolo import _check_weights_path, _import_ultralytics, ultralytics_device_of

        p = _check_weights_path(weights)
        _import_ultralytics()
        from ultralytics import YOLO

        try:
            self.model = YOLO(str(p.resolve()))
        except Exception as e:  # many exception types for a bad checkpoint; one clear line
            raise PavemapError(f"{p}: cannot load YOLO weights ({type(e).__name__}: {e})") from None
        if self.model.task != "semantic":
            raise PavemapError(
                f"{p}: these are YOLO '{self.model.task}' weights; the segmenter needs 'semantic' "
                "segmentation weights (e.g. a YOLO26-sem model trained on road classes)"
            )
        self.label_map = class_map if isinstance(class_map, LabelMap) else load_label_map(class_map)
        self.classes: list[SemanticClass] = list(self.label_map.classes)
        names = self.model.names
        other = next((c.id for c in self.classes if c.name == "other"), None)
        lut = np.full(256, 255 if other is None else other, dtype=np.uint8)
        unknown = []
        for i, n in names.items():
            tid = self.label_map.names.get(_norm(n))
            if tid is None:
                unknown.append(n)
                if other is None:
                    raise PavemapError(
                        f"model class {n!r} has no class in map {self.label_map.name!r} and the map has no "
                        "'other' class; add it under 'names:' in the class map YAML"
                    )
            else:
                lut[int(i)] = tid
        if unknown:
            log.info("segmenter classes mapped to 'other': %s", ", ".join(map(str, unknown)))
        self.lut = lut
        self.imgsz = imgsz
        self.device = ultralytics_device_of(device)

    def segment(self, images: list[np.ndarray]) -> list[np.ndarray]:
        """(H, W, 3) uint8 RGB each → (H, W) uint8 label-table ids each, at the original resolution."""
        bgr = [np.ascontiguousarray(im[:, :, ::-1]) for im in images]
        res = self.model.predict(bgr, imgsz=self.imgsz, device=self.device, verbose=False, batch=len(bgr))
        out = []
        for im, r in zip(images, res, strict=True):
            m = r.semantic_mask.data
            m = m.cpu().numpy() if hasattr(m, "cpu") else np.asarray(m)
            if m.shape != im.shape[:2]:
                raise PavemapError(f"segmenter returned a {m.shape} mask for a {im.shape[:2]} image")
            out.append(self.lut[np.clip(m.astype(np.int64), 0, 255)])
        return out
