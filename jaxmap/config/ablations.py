"""The N3 map's ablations and earlier defaults, by name: `--set` overrides of `configs/city.yaml` that
`jaxmap bench n3 --only NAME` runs, and notebooks/02_ablation compares (the paper's Table III and ours)."""

VARIANTS = {
    "jaxmap": [],
    # free space before issue 30: no persistent evidence, no veil filter (ray samples and carving only)
    "evidence_off": ["evidence.enabled=false", "preprocess.veil_m=0"],
    "veil_off": ["preprocess.veil_m=0"],                # evidence, but mixed pixels and outliers kept
    "no_raise": ["evidence.raise_pairs=false"],         # void voxels masked, their pairs left as they were
    # the evidence alone: no free samples along the ray, nothing carved (issue 21's mechanism off)
    "no_rays": ["sampling.free_ray_n=0", "window.carve=false"],
    "void2": ["evidence.void_frames=2"],                # void after two frames seen free, not one
    # the free-space label and pair store before issue 14 (flat +tr free labels, newest-64 ring)
    "flat_ring": ["sampling.free_label_mode=truncation", "window.block_policy=ring", "window.pairs_per_frame=0"],
    # free space before issue 21: samples only in the last metre before the band, nothing carved
    "band_only": ["sampling.free_ray_n=0", "window.carve=false"],
    "no_carve": ["window.carve=false"],                  # samples along the ray, but nothing carved
    "ray_only": ["sampling.free_sample_n=0"],           # the paper's rule: every free sample on the whole ray
    "sigma_0.1": ["sampling.sigma_m=0.1"],              # the paper's tr / 3
    "outliers": ["preprocess.outlier_mad=6"],           # range-scaled statistical outlier removal
    # the scan preprocessed inside the frame program (k nearest in the grid's cubes; whole-cube PCA)
    "device": ["preprocess.device=true", "preprocess.normals=cube_knn"],
    "device_grid": ["preprocess.device=true", "preprocess.normals=grid"],
    # the k nearest of each point's range-image neighbours (the scan's own organisation), on the device / host
    "device_range": ["preprocess.device=true", "preprocess.normals=range_image"],
    "range_image": ["preprocess.normals=range_image"],
    "projective": ["sampling.label_mode=projective"],
    "corrected": ["sampling.label_mode=corrected"],
    "replay": ["window.mode=replay"],
    "keyframe": ["window.mode=keyframe"],
    "no_hier": ["train.hierarchical=false"],
}
# what a plain `jaxmap bench n3` runs (the others are run by name, with --only, mostly on the suite)
