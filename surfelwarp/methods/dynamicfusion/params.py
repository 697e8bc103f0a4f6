"""Every DynamicFusion baseline parameter in one frozen tree (config.py overrides it from a file)."""
from __future__ import annotations

from dataclasses import asdict, dataclass, field

from surfelwarp.deform.warp_field import WarpFieldParams
from surfelwarp.methods.dynamicfusion.tsdf import TSDFParams
from surfelwarp.tracking.tracker import TrackingParams


@dataclass(frozen=True)
class DynamicFusionParams:
    tsdf: TSDFParams = field(default_factory=TSDFParams)
    # node_radius_m is DynamicFusion's decimation density epsilon (25 mm, Sec. 4).
    warp_field: WarpFieldParams = field(default_factory=WarpFieldParams)
    # The same tracker as SurfelWarp, its nodes carried on by their last steps too
    # (predict_node_motion; the paper starts each frame where the last one ended).
    tracking: TrackingParams = field(default_factory=TrackingParams)
    min_first_points: int = 500       # the model starts at the first frame with this many valid pixels
    voxel_chunk: int = 1 << 18        # voxels per warp / skinning batch (bounds temporaries)
    # Warp and fuse only blocks of voxels that can be fused this frame (fusible_blocks): the
    # same result as warping every voxel, at a fraction of the cost.
    cull_voxels: bool = True
    cull_block: int = 6               # block edge, voxels (4-8 all cost about the same)
    cull_margin_m: float = 0.004      # slack for the blend leaving the hull of its nodes' motions

    ZERO_OK = {"min_first_points", "cull_margin_m"}
    AT_MOST = {"cull_block": 64}

    def to_dict(self) -> dict:
        return asdict(self)
