"""Classical baselines run on the same data and meshed on the same lattice as the neural maps
(docs/evaluation.md).

- `jaxmap.baselines.tsdf`: TSDF fusion of range scans with the VDBFusion ray update
  (`tsdf_from_sequence`, `TSDFVolume`); `jaxmap baseline tsdf DATA --voxel 0.2 --out MESH`.

Submodules are imported lazily (open3d-free; numpy/scipy/scikit-image/trimesh only).
"""
