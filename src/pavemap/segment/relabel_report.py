"""What a pass that relabels a segmenter's road pixels did (the plane check, the road vote)."""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass
class RelabelReport:
    """Counts over a drive's views: ``views`` seen, ``road_px`` road pixels of the judged ones, ``relabelled_px`` of
    them relabelled, ``skipped`` short reasons (camera or view: why)."""

    views: int = 0
    road_px: int = 0
    relabelled_px: int = 0
    skipped: list[str] = field(default_factory=list)

    @property
    def share(self) -> float:
        """The share of the judged views' road pixels relabelled."""
        return self.relabelled_px / max(self.road_px, 1)
