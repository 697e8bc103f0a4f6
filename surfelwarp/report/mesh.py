"""`surfelwarp mesh OUT [--frame N]`: the triangle mesh of a run's model or of a saved live frame."""
from __future__ import annotations

from pathlib import Path

from surfelwarp.errors import InputError
from surfelwarp.geometry.surfel_mesh import mesh_of
from surfelwarp.io.ply import mesh_table, read_ply, write_ply


def mesh_run(out_dir: Path, frame: int | None = None, voxel_m: float | None = None) -> Path:
    """OUT/model_mesh.ply from OUT/model.ply, or OUT/mesh/frame-%06d.ply from that live frame
    (in the same camera frame as the PLY it is made from); the path written."""
    out_dir = Path(out_dir)
    if frame is None:
        source, target = out_dir / "model.ply", out_dir / "model_mesh.ply"
    else:
        source, target = out_dir / "live" / f"frame-{frame:06d}.ply", out_dir / "mesh" / f"frame-{frame:06d}.ply"
    if voxel_m is not None and not 0 < voxel_m < 1:
        raise InputError(None, f"--voxel-size must be in (0, 1) metres, got {voxel_m}")
    if not source.is_file():
        saved = sorted(p.stem[len("frame-"):] for p in (out_dir / "live").glob("frame-*.ply"))
        hint = f" (saved frames: {', '.join(str(int(s)) for s in saved)})" if saved and frame is not None else ""
        raise InputError(source, f"no such file{hint}")
    try:
        table, faces = read_ply(source)
        mesh = mesh_of(table, faces, voxel_m)
    except (ValueError, KeyError, IndexError, OSError, UnicodeDecodeError) as exc:
        raise InputError(source, f"cannot read the PLY ({exc.__class__.__name__})") from None
    write_ply(target, mesh_table(mesh.vertices, mesh.normals, mesh.colors), mesh.faces)
    return target
