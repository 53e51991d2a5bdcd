"""Synthetic sequences with exact ground truth.

* `generate_city(out_dir, ...)`: MaiCity-like street scene (a street grid, or `layout="suburb"`: a ring
  boulevard with detached houses), ray-cast 64-beam LiDAR, KITTI layout.
* `generate_room(out_dir, ...)`: indoor room, pinhole depth camera, depth layout.

Both are deterministic from `seed`, write `gt_mesh.ply` / `gt_points.ply` / `meta.json`, and return
the stats of meta.json. open3d (ray casting) is imported only when a scene is generated.
"""
from jaxmap.synth.city import generate_city
from jaxmap.synth.room import generate_room

__all__ = ["generate_city", "generate_room"]
