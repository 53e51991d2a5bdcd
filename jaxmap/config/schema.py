"""The config schema of every command: frozen dataclasses, one per section, and the roots that hold them
(`MapConfig` for `jaxmap map`, `ImtConfig` for `jaxmap imt`). A field's comment says what it means; the
reference page of every key (docs/configuration.md) is generated from these classes
(`jaxmap.config_reference`). Value rules live in `jaxmap.config.rules`, loading in `jaxmap.config.loading`.
"""
from __future__ import annotations

from dataclasses import dataclass, field

# ---------------------------------------------------------------------------------------------
# The N3 mapping config (jaxmap map). Names follow SHINE-Mapping / N3-Mapping where they exist.
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class DataConfig:
    path: str = "data/city"          # sequence directory or file (KITTI, depth, ROS bag, TUM RGB-D, Replica, LAS/LAZ)
    kind: str = "auto"               # "auto", "kitti" (LiDAR scans), "depth" (depth images), "rosbag" (.bag/.mcap/.db3
                                     # or ROS 2 bag directory), "tum" (TUM RGB-D), "replica" or "las" (LAS/LAZ)
    topic: str = ""                  # ROS bag: the sensor_msgs/PointCloud2 topic to map ("" = the bag's only one)
    begin_frame: int = 0             # first frame to map (index into the sequence)
    end_frame: int = -1              # exclusive; -1 = to the end
    every_frame: int = 1             # map every n-th frame (1 = all)


@dataclass(frozen=True)
class PreprocessConfig:
    min_range_m: float = 1.5         # points closer to the sensor are dropped (ego vehicle)
    max_range_m: float = 20.0        # "pc_radius_m" of the anchors: crop radius
    min_z_m: float = -10.0           # height crop in the sensor frame
    max_z_m: float = 30.0            # upper height crop in the sensor frame
    vox_down_m: float = 0.05         # voxel downsample before sampling (0 = off)
    normal_knn: int = 20             # neighbours for PCA normals (grid: the fewest points a neighbourhood must hold)
    normals: str = "knn"             # "knn" (k nearest neighbours, scipy on the host), "cube_knn" (the k nearest
                                     # among the points of a hashed-grid cube), "grid" (all of the cube) or
                                     # "range_image" (the k nearest of the scan's range-image neighbours)
    normal_cell_m: float = 0.15      # grid normals: the finest cell; a point's neighbourhood is 2 x 2 x 2 cells
    normal_levels: int = 3           # grid normals: cell sizes normal_cell_m * 2^l, l < this (the finest with >= knn)
    device: str = "auto"             # preprocess inside the frame program, on the device: true | false | auto (the
                                     # device on a GPU or TPU, the host on a CPU); there normals knn becomes cube_knn
    outlier_mad: float = 0.0         # > 0: drop points whose range-scaled mean neighbour distance is this many
                                     # robust std above the scan's median (mixed pixels, stray returns); 0 = off
    veil_m: float = 0.15             # > 0: drop mixed pixels and isolated returns on the scan's range image (a
                                     # return that continues no neighbour in its row or column within this); 0 = off
    image_rows: int = 0              # the scan's range image (veil filter, free-space evidence): rows (beams);
                                     # 0 = read off the first scan (its elevation clusters), then fixed for the run
    image_cols: int = 0              # ... columns (azimuth steps a turn); 0 = read off the first scan
    image_elev0_deg: float = 0.0     # ... elevation of row 0's lower edge (degrees; set with image_rows)
    image_elev_step_deg: float = 0.0  # ... rows' height (degrees; set with image_rows)
    image_az0_deg: float = -180.0    # ... azimuth where column 0 starts (degrees; set with image_rows)
    image_beams_deg: tuple[float, ...] = ()  # ... a spinning LiDAR's beam table: every beam's elevation (degrees),
                                     # one row per beam (a return goes to the nearest beam); () = read off the
                                     # first scan (with image_rows 0) or a uniform grid (image_rows > 0: a sensor
                                     # without beams); set it when the first scan is too sparse to read it


@dataclass(frozen=True)
class SamplingConfig:
    label_mode: str = "normal"       # "normal" (N3), "projective", "corrected" (ablations)
    surface_sample_range_m: float = 0.3   # truncation band half-width (tr)
    surface_sample_n: int = 3        # near-surface samples per scan point, inside the truncation band
    sigma_m: float = 0.05            # std of the Gaussian offset inside the band (~ range noise)
    free_sample_n: int = 3           # free-space samples per scan point, on the ray before the band
    free_band_m: float = 1.0         # free samples lie in the last free_band_m before the band
    free_ray_n: int = 6              # more free samples per scan point, stratified along the whole ray
                                     # (from preprocess.min_range_m to the band): they carve what moved
    free_ray_quiet_frames: int = 10  # ... in voxels no frame has hit within this many frames (static surfaces are
                                     # hit again and again; a ray's label is honest only about its own hit)
    free_label_m: float = -1.0       # label of free-space samples; <0 means "= truncation"
    free_point_filter_m: float = 0.0  # > 0: scan points where the map so far has an SDF above this (confidently
                                     # free: something moved in, a mixed pixel) get no samples; 0 = off
    free_label_mode: str = "projected"  # "projected": that label capped by the distance to the hit's
                                        # tangent plane; "truncation": the label as is (paper; ablation)


@dataclass(frozen=True)
class GridConfig:
    leaf_vox_size: float = 0.2       # edge length of the leaf (finest) voxels, metres
    feature_levels: int = 3          # levels of corner features; level l has voxels of edge `leaf_vox_size * 2**l`
    feature_dim: int = 8             # feature channels per corner
    feature_std: float = 1e-4        # features initialised N(0, std)
    max_load: float = 0.5            # grow (rehash, outside jit) past this load factor


@dataclass(frozen=True)
class DecoderConfig:
    hidden_dim: int = 32             # width of the SDF decoder's hidden layers
    hidden_layers: int = 2           # hidden layers of the SDF decoder (ReLU)


@dataclass(frozen=True)
class TrainConfig:
    iters: int = 50                  # K iterations per frame
    nv: int = 1024                   # voxels per iteration (hierarchical stage 1)
    np_per_voxel: int = 8            # pairs per voxel (stage 2)
    nt: int = 10                     # voxels with fewer pairs get np/3
    hierarchical: bool = True        # False = uniform pairs (ablation)
    batch_size: int = 8192           # pairs per iteration when hierarchical is False
    lr: float = 0.01                 # Adam learning rate of the features and the decoder
    sigma_sigmoid_m: float = 0.1     # beta of the BCE sigmoid
    weight_e: float = 0.08           # eikonal weight
    freeze_after_frame: int = 20     # decoder frozen after this many frames
    reset_adam_each_frame: bool = False # restart the Adam moments every frame (as the original N3 code does)
    seed: int = 0                    # PRNG seed: feature and decoder initialisation, sampling


@dataclass(frozen=True)
class WindowConfig:
    mode: str = "voxel"              # "voxel" (N3), "replay" (all past pairs, drawn uniformly),
                                     # "keyframe" (the pairs of the last N frames, drawn uniformly)
    keyframes: int = 5               # window length for mode "keyframe"
    pairs_per_voxel: int = 64        # block capacity (pairs kept per leaf voxel)
    block_policy: str = "reservoir"  # "reservoir": a uniform sample of the pairs the voxel received in the
                                     # window; "ring": the newest pairs (ablation)
    pairs_per_frame: int = 8         # at most this many of a frame's pairs offered to a voxel (0 = all)
    initial_blocks: int = 1 << 14    # blocks in the store at start (grown outside jit when full)
    carve: bool = True               # free space along the ray replaces the stored pairs it contradicts
                                     # (needs sampling.free_ray_n > 0): erases what moved away
    carve_margin_m: float = 0.05     # a stored pair is contradicted when its label < free label - distance - this
    carve_samples: int = 16384       # at most this many usable ray samples a frame train and carve (fixed-size buffers)
    carve_rule: str = "replace"      # "replace": a free sample takes the place of the pair it contradicts most;
                                     # "raise": every contradicted pair's label rises to the Lipschitz bound
    carve_sign: bool = False         # also: every ray sample (it is outside every object) raises the pairs stored
                                     # deeper inside than |x - y| + margin, in any voxel, recently hit or not


@dataclass(frozen=True)
class EvidenceConfig:
    enabled: bool = True             # persistent free-space evidence per leaf voxel: voxels seen free (every
                                     # return of their footprint in the range image lies beyond them) since their
                                     # last hit are void: no training on points there, their pairs raised, no mesh
    margin_m: float = 0.1            # a voxel is seen free when every return near its direction lies beyond its
                                     # far side by this (pose and range error; DUFOMap's margin)
    void_frames: int = 1             # frames seen free since the last hit that make a voxel void
    max_range_m: float = 40.0        # voxels within this of the sensor are tested each frame (those their own
                                     # pixel may free, up to 65,536; more: a different part each frame)
    raise_pairs: bool = True         # the pairs stored in a voxel that turns void are raised to >= margin_m


@dataclass(frozen=True)
class SubmapsConfig:
    enabled: bool = False            # the map is a chain of N3 submaps (each an N3 map of its own), the far
                                     # ones written to the run's submaps/ and dropped from memory: a drive of any
                                     # length in bounded memory
    length_m: float = 60.0           # a new submap starts when the sensor is this far from the current one's
                                     # first frame (or an earlier one's first frame within half of it is taken up again)
    blend_m: float = 4.0             # a query reads every submap that holds it within this of the nearest
                                     # one (distance to the submaps' sensor paths), weights falling linearly to 0
    resident: int = 1                # submaps held in memory at once, the one mapped included (the rest on disk)
    auto_m: float = 300.0            # enabled false: `jaxmap map` maps a drive whose path (its poses) is longer
                                     # than this in submaps all the same (0: never; the suite's streets are 125-136 m,
                                     # a 1.1 km drive in one grid peaked at 6.7 GB)
    revisit: bool = True             # a drive back takes up the earlier submap there; false: a new submap once
                                     # the sensor has driven length_m in the current one, so every pass maps into
                                     # submaps of its own, blended (jaxmap slam's: a loop correction moves them
                                     # apart as rigid bodies)


@dataclass(frozen=True)
class MeshConfig:
    resolution_m: float = 0.1        # marching-cubes lattice spacing, metres (must divide leaf_vox_size)
    min_component_faces: int = 50    # drop connected components smaller than this
    mask_level: int = 1              # mesh inside allocated voxels of this feature level (0 = leaf)
    min_leaf_corners: int = 6        # ... where at least this many leaf-voxel corners have features


@dataclass(frozen=True)
class EvalConfig:
    threshold_m: float = 0.1         # F-score threshold
    cull_distance_m: float = 0.3     # GT points farther than this from every scan point are culled
    eval_radius_m: float = -1.0      # >0: keep GT within this radius of some sensor position
    n_samples: int = 10_000_000      # points sampled on the cropped predicted mesh (SHINE: 10M)


@dataclass(frozen=True)
class MapConfig:
    """Root config of `jaxmap map` (N3-Mapping)."""

    data: DataConfig = field(default_factory=DataConfig)
    preprocess: PreprocessConfig = field(default_factory=PreprocessConfig)
    sampling: SamplingConfig = field(default_factory=SamplingConfig)
    grid: GridConfig = field(default_factory=GridConfig)
    decoder: DecoderConfig = field(default_factory=DecoderConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    window: WindowConfig = field(default_factory=WindowConfig)
    evidence: EvidenceConfig = field(default_factory=EvidenceConfig)
    submaps: SubmapsConfig = field(default_factory=SubmapsConfig)
    mesh: MeshConfig = field(default_factory=MeshConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)
    output: str = "runs/map"         # run directory (`--out` overrides it)
    checkpoint_every: int = 50       # frames between checkpoints (also written at the end and on Ctrl-C or SIGTERM)


# ---------------------------------------------------------------------------------------------
# The transformable latent map config (jaxmap imt, jaxmap slam); indoor settings of the IMT paper.
# ---------------------------------------------------------------------------------------------


def _room_data() -> DataConfig:
    return DataConfig(path="data/room", every_frame=2)


def _room_preprocess() -> PreprocessConfig:
    return PreprocessConfig(min_range_m=0.1, max_range_m=8.0, vox_down_m=0.025, veil_m=0.0)


@dataclass(frozen=True)
class LatentMapConfig:
    voxel_size_m: float = 0.1         # PLIVox side (IMT paper: 0.1 m indoors)
    min_points: int = 10              # voxels fed by fewer points of a frame are dropped
    interpolation: str = "trilinear"  # "trilinear" (splat, weight-conserving) or "softmax" (paper eq. 9)
    jacobian_sign: float = -1.0       # first-order term F - J t (-1); +1 = the paper's eq. 5; 0 = none
    softmax_temperature: float = 1.0  # softmax only: weights exp(-|t|^2 / T), t in voxel units
    k_neighbours: int = 8             # softmax only: local voxels gathered per global voxel
    splat_power: float = 2.0          # trilinear only: splat weights^power, renormalised (1 = plain trilinear)
    remap_min_rotation_deg: float = 0.05  # remap a keyframe whose pose moved more than this ...
    remap_min_translation_m: float = 0.002  # ... or this
    remap_rebuild_fraction: float = 0.5  # rebuild the map from every keyframe when more than this share moved
    remap: str = "reencode"           # keyframes keep pooled cells, re-encoded at the new pose | "transform":
                                      # they keep latent local maps, moved with Jacobians (jaxmap bench imt)
    cells_per_voxel: int = 1          # points are pooled into cells of voxel / this before encoding (0 = none)
    transform_cells_per_voxel: int = 2  # the same for local maps encoded with Jacobians (for `transform`)
    initial_capacity: int = 16384     # hash-table slots of the global map at start (grows, logged)
    prior: str = ""                   # prior weights (.npz); "" = the weights shipped in the package


@dataclass(frozen=True)
class LatentMeshConfig:
    resolution: int = 4               # marching-cubes lattice points per voxel side (even)
    sigma_threshold_m: float = 0.15   # drop triangles where the decoded SDF std exceeds this (<= 0: keep all)
    min_weight: float = 10.0          # voxels with less observation weight are not meshed
    min_component_faces: int = 0      # drop connected components smaller than this


@dataclass(frozen=True)
class ImtConfig:
    """Root config of `jaxmap imt` (transformable neural implicit map)."""

    data: DataConfig = field(default_factory=_room_data)
    preprocess: PreprocessConfig = field(default_factory=_room_preprocess)
    map: LatentMapConfig = field(default_factory=LatentMapConfig)
    mesh: LatentMeshConfig = field(default_factory=LatentMeshConfig)
    eval: EvalConfig = field(default_factory=lambda: EvalConfig(threshold_m=0.05, cull_distance_m=0.1,
                                                                n_samples=1_000_000))
    output: str = "runs/imt"            # run directory (`--out` overrides it)
    progress: bool = True             # tqdm progress bar
