"""Log records held back while two candidate paths are measured, so that only the kept path's reach the user.

:func:`pavemap.sfm.pipeline.sfm_poses` scales COLMAP's path and, where COLMAP needed repairs, the car's planar
motion too, then keeps one. Each scaling logs its own warnings (the road's step lengths and the dense ground
points disagreeing, steps the road could not measure). Printed as they come, the discarded path's warnings read
as the result's: on clips 1 + 2 joined in time order the console said "disagree on the scale by +15 %" of a
COLMAP path that was then replaced by one whose two scales agree within 0.4 %.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Iterator

SFM_LOGGER = "pavemap.sfm"


class _Holder(logging.Handler):
    def __init__(self) -> None:
        super().__init__(logging.NOTSET)
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append(record)


@contextlib.contextmanager
def held_records(name: str = SFM_LOGGER) -> Iterator[list[logging.LogRecord]]:
    """Records logged under ``name`` inside the block are collected into the yielded list instead of reaching
    the handlers; on an exception they are replayed first (a refusal's reasons must not vanish)."""
    logger = logging.getLogger(name)
    holder, propagate = _Holder(), logger.propagate
    logger.addHandler(holder)
    logger.propagate = False
    try:
        yield holder.records
    except BaseException:
        _restore(logger, holder, propagate)
        replay(holder.records)
        raise
    _restore(logger, holder, propagate)


def _restore(logger: logging.Logger, holder: _Holder, propagate: bool) -> None:
    logger.removeHandler(holder)
    logger.propagate = propagate


def replay(records: list[logging.LogRecord]) -> None:
    """Hand held records to their loggers' handlers now, in the order they were logged."""
    for r in records:
        logging.getLogger(r.name).handle(r)


def warnings_of(records: list[logging.LogRecord]) -> list[str]:
    """The messages of the held records at WARNING or above (kept in ``sfm.json`` for the path not kept)."""
    return [r.getMessage() for r in records if r.levelno >= logging.WARNING]


__all__ = ["held_records", "replay", "warnings_of"]
