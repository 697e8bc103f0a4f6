"""Every SurfelWarp parameter in one frozen tree (config.py overrides it from a file)."""
from __future__ import annotations

from dataclasses import asdict, dataclass, field

from surfelwarp.deform.warp_field import WarpFieldParams
from surfelwarp.methods.surfelwarp.appending import AppendParams
from surfelwarp.methods.surfelwarp.fusion import FusionParams
from surfelwarp.methods.surfelwarp.reinit import ReinitParams
from surfelwarp.tracking.tracker import TrackingParams


@dataclass(frozen=True)
class SurfelWarpParams:
    warp_field: WarpFieldParams = field(default_factory=WarpFieldParams)
    tracking: TrackingParams = field(default_factory=TrackingParams)
    fusion: FusionParams = field(default_factory=FusionParams)     # Sec. VI-A, VI-D removal
    append: AppendParams = field(default_factory=AppendParams)     # Sec. VI-B..D appending
    reinit: ReinitParams = field(default_factory=ReinitParams)     # Sec. VI-F
    # Solver maps draw the stable surfels (fusion.stable_confidence = delta_stable) first.
    # recent_draw 'fill_all': every other surfel only on pixels no stable surfel covers, so
    # fresh surfels (carrying last frame's pose error) never occlude the stable model, while
    # newly seen surface and the not yet stable model are tracked (a young model is all
    # unstable: a free sheet's edges, never observed again once they overhang, left the solve
    # and the sheet slid, EPE 61 mm against 22 mm); 'fill': only those observed within the
    # last recent_frames frames (delta_recent, Table 1); 'with': stable and recent in one
    # depth test.
    recent_frames: int = 2
    recent_draw: str = "fill_all"
    index_map_supersample: int = 4   # Sec. VI-A: 4x4 super-sampled index map

    CHOICES = {"recent_draw": ("fill", "fill_all", "with")}
    ZERO_OK = {"recent_frames"}
    AT_MOST = {"index_map_supersample": 8}

    def to_dict(self) -> dict:
        return asdict(self)
