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
    # Solver maps draw each surfel's disk cut to this radius in pixels at its depth (0: whole).
    # Eq. 4's radius is sqrt(2) pixels at capture (more on oblique views), and surfels seen
    # nearer than where they were captured grow with it: on 7-Scenes the drawn disks' median
    # radius is 3.3 px, ~22 a pixel, and the maps took 110-170 ms a frame. The authors' code
    # draws a square of the disk's smaller projected extent (or one pixel). At 2 px the maps
    # take half the time and leave 1.2-1.3 % of the pixels empty that a whole disk covered.
    solver_splat_max_px: float = 2.0
    index_map_supersample: int = 4   # Sec. VI-A: 4x4 super-sampled index map

    CHOICES = {"recent_draw": ("fill", "fill_all", "with")}
    ZERO_OK = {"recent_frames", "solver_splat_max_px"}
    AT_MOST = {"index_map_supersample": 8}

    def to_dict(self) -> dict:
        return asdict(self)
