"""What the run's read-ahead worker found before a frame, kept by observation.

The worker is one frame ahead, so a frame's own observation and the next one's are all there is
to keep: two, by identity (a frame left out never piles up). The worker replaces the whole tuple
and the frame reads it whole, so no lock is needed; a checkpoint keeps none of it.
"""
from __future__ import annotations

from typing import Any


class FoundAhead:
    def __init__(self):
        self._kept: tuple[tuple[Any, Any], ...] = ()

    def put(self, obs: Any, found: Any) -> None:
        self._kept = self._kept[-1:] + ((obs, found),)

    def get(self, obs: Any) -> Any | None:
        """What was found for this very observation, or None."""
        return next((found for seen, found in self._kept if seen is obs), None)

    def observations(self) -> list:
        return [seen for seen, _ in self._kept]

    def __getstate__(self) -> dict:
        return {"_kept": ()}
