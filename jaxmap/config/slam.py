"""The config of `jaxmap slam`: its front end (odometry, loop closure, keyframes, pose graph) and the root
`SlamConfig`, which adds the front end to the transformable map's sections (`jaxmap.config.schema`)."""
from __future__ import annotations

from dataclasses import dataclass, field

from jaxmap.config.schema import (DataConfig, EvalConfig, ImtConfig, LatentMapConfig, LatentMeshConfig,
                                  PreprocessConfig)

ODOMETRY_METHODS = ("icp", "kiss_icp")
EDGE_INFORMATION = ("isotropic", "icp")
MAP_KINDS = ("imt", "n3")
N3_LOOP_MODES = ("submaps", "rebuild", "moved", "none")
# the LiDAR's levelling by its scans' vertical surfaces (`jaxmap.slam.level`), chosen on `jaxmap bench slam
# --suite` (docs/slam.md): the whole tilt each frame, the up direction from the first frame's facades
LIDAR_LEVEL_GAIN = 1.0
LIDAR_LEVEL_REFERENCE_FRAMES = 10


@dataclass(frozen=True)
class OdometryConfig:
    """Odometry parameters. Defaults suit the indoor depth camera (room: 0.2-10 m ranges, mm noise):
    3 cm voxels and correspondences within 2 voxels. Measured on the 40-frame room with 5 mm noise:
    3 cm / 6 cm gives 0.4 cm ATE at ~0.2 s per frame (2 CPU cores); 5 cm / 10 cm 0.8 cm at ~0.1 s;
    a wider correspondence distance (3 voxels) is faster to converge but biased: 2x the drift.

    For a street LiDAR (the city, 50 m range, cm noise) use `OdometryConfig.lidar()`: KISS-ICP (method
    kiss_icp), and for ICP (and the scans kept for loop closure) voxel 0.3 m, correspondences within
    0.6 m (1.5 m in the coarse stage), fitness >= 0.5, RMSE <= 0.4 m (the point-to-point RMSE of a
    correct match of sparse beams is already ~0.25 m, so fitness is the real test). Odometry ATE on the
    10 Hz cities with 2 cm noise (`jaxmap bench slam --only odometry`): KISS-ICP 2.8 cm, ICP 14.7 cm
    (city, 130 frames, 125 m); KISS-ICP 9.6 cm, ICP 9.1 cm (small city, 64 frames, 62 m). ICP's 0.3 m
    voxels are the sensible middle of 0.2-0.5 m for 32-64 beams (0.2 m: twice the time).

    method:         "icp": this module's frame-to-frame point-to-plane ICP (open3d), the default (the depth
                    camera's); "kiss_icp": KISS-ICP (Vizzo et al., RA-L 2023; `pip install kiss-icp`),
                    point-to-point ICP against a voxel-hashed local map with an adaptive threshold
                    (`jaxmap.slam.kiss`), the LiDAR default (`lidar()`). Both give the same OdomStep; the
                    scans kept for loop closure are prepared with the fields below either way
    kiss_voxel_m:   kiss_icp only: voxel size of its local map (m); 0 = max_range_m / 100 as KISS-ICP does
    kiss_initial_threshold_m: kiss_icp only: KISS-ICP's adaptive threshold (its kernel; correspondences
                    within 3x) until it has measured how far its predictions miss. jaxmap seeds the first
                    step with its own ICP (`jaxmap.slam.kiss`), so the first prediction is already close:
                    0.3 m (ATE 2.8 / 9.6 cm on the 10 Hz city / small city) instead of KISS-ICP's 2.0 m,
                    made for a first step from no motion (15.5 / 39 cm: the wide kernel keeps the pull of
                    the road's beam rings towards no motion); 0.5 m gave 4.4 / 11.7 cm. Without a seed
                    (its ICP fails) KISS-ICP's 2.0 m is used
    voxel_m:        downsampling voxel (m) of the scans fed to ICP (and to the loop verification)
    max_corr_m:     ICP correspondence distance of the fine stage (m); about 2 voxels
    coarse_factor:  a first ICP stage runs with voxel and max_corr scaled by this (1 = single stage);  # a first ICP stage runs with voxel and max_corr scaled by this (1 = one stage)
                    it widens the basin of convergence when the motion prior is off
    retry_below_fitness: when ICP from the motion prior reaches a lower fitness, a global registration
                    (FPFH + RANSAC, then ICP) is tried too and the better-fitting result kept; 0 disables.
                    It rescues sharp turns and the first step, where constant velocity is a poor guess
    min_fitness:    ICP result rejected below this fraction of matched source points
    max_rmse_m:     ICP result rejected above this inlier RMSE (m)
    max_iter:       ICP iterations per stage
    normals_k:      neighbours for the PCA normals
    min_points:     fewer downsampled points than this -> the frame is not registered
    min_range_m, max_range_m: range crop of the input scan (m)
    """
    method: str = "icp"                 # "icp" (open3d point-to-plane, frame to frame) or "kiss_icp" (KISS-ICP, frame to local map)
    kiss_voxel_m: float = 0.0           # kiss_icp: voxel (m) of its local map; 0 = max_range_m / 100 (KISS-ICP's default)
    kiss_initial_threshold_m: float = 0.3  # kiss_icp: adaptive threshold (m) before any measured deviation (KISS-ICP: 2.0)
    voxel_m: float = 0.03               # downsampling voxel (m) of the scans fed to ICP
    max_corr_m: float = 0.06            # ICP correspondence distance of the fine stage (m); about 2 voxels
    coarse_factor: float = 2.5          # a first ICP stage runs with voxel and max_corr scaled by this (1 = one stage)
    retry_below_fitness: float = 0.8    # below this fitness a global registration (FPFH + RANSAC) is tried too; 0 = never
    min_fitness: float = 0.5            # ICP rejected below this fraction of matched source points
    max_rmse_m: float = 0.04            # ICP rejected above this inlier RMSE (m)
    max_iter: int = 30                  # ICP iterations per stage
    normals_k: int = 15                 # neighbours for the PCA normals
    min_points: int = 100               # fewer downsampled points than this: the frame is not registered
    min_range_m: float = 0.1            # range crop of the input scan (m), near
    max_range_m: float = 10.0           # range crop of the input scan (m), far

    @classmethod
    def lidar(cls, **overrides) -> "OdometryConfig":
        """Settings for a street LiDAR (see the class docstring); keyword arguments override them."""
        base = dict(method="kiss_icp", voxel_m=0.3, max_corr_m=0.6, coarse_factor=2.5, retry_below_fitness=0.8,
                    min_fitness=0.5, max_rmse_m=0.4, normals_k=15, min_range_m=2.0, max_range_m=50.0)
        base.update(overrides)
        return cls(**base)


@dataclass(frozen=True)
class LoopConfig:
    """Loop-closure parameters. Defaults suit the indoor depth camera; `LoopConfig.lidar()` the street LiDAR.

    radius_m:           candidates are keyframes whose estimated position is within this distance (m)
    min_gap:            ... and at least this many keyframes before the current one
    max_candidates:     at most this many candidates are verified per keyframe (nearest first)
    max_corr_m:         correspondence distance (m) of the first ICP stage; a second stage uses half.
                        It must exceed the drift expected at the loop
    fine_corr_m:        distance (m) of a last ICP stage that gives T_rel and its information; about
                        2 voxels of the clouds (as OdometryConfig.max_corr_m): wider ones bias the result
    min_fitness:        minimum overlap fraction, required both ways, at the second-stage distance
    max_rmse_m:         maximum inlier RMSE (m) at the second-stage distance
    max_correction_m, max_correction_deg: largest accepted ICP correction of the initial guess
    min_constraint:     smallest accepted eigenvalue of the translation block of the point-to-plane
                        normal matrix, per correspondence (0..1; 1/3 for evenly spread normals)
    max_conflict:       largest accepted fraction of points in the other scan's free space (either way)
    free_space_margin_m: a point is in free space when it is this much (+10 % of the range) in front of
                        the nearest return of the other scan in its direction
    free_space_res_deg: angular bin of the range images for the free-space test
    max_iter:           ICP iterations per stage
    """
    radius_m: float = 1.0               # candidates: keyframes whose estimated position is within this distance (m)
    min_gap: int = 10                   # ... and at least this many keyframes back
    max_candidates: int = 3             # at most this many candidates verified per keyframe (nearest first)
    max_corr_m: float = 0.3             # correspondence distance (m) of the first ICP stage; must exceed the drift at the loop
    fine_corr_m: float = 0.06           # correspondence distance (m) of the last, fine ICP stage
    min_fitness: float = 0.6            # minimum overlap fraction, required both ways
    max_rmse_m: float = 0.06            # maximum inlier RMSE (m) of the fine stage
    max_correction_m: float = 0.5       # largest accepted ICP correction of the initial guess (m)
    max_correction_deg: float = 15.0    # largest accepted ICP correction of the initial guess (deg)
    min_constraint: float = 0.005       # smallest eigenvalue of the point-to-plane translation block per correspondence
    max_conflict: float = 0.03          # largest fraction of points in the other scan's free space (either way)
    free_space_margin_m: float = 0.05   # a point is in free space this far (+10 % of range) in front of the other scan
    free_space_res_deg: float = 1.0     # angular bin of the range images of the free-space test
    max_iter: int = 40                  # ICP iterations per stage

    @classmethod
    def lidar(cls, **overrides) -> "LoopConfig":
        """Street-LiDAR settings (0.3 m voxels, metres of drift over a block); keywords override them."""
        base = dict(radius_m=10.0, min_gap=8, max_candidates=3, max_corr_m=2.0, fine_corr_m=0.6, min_fitness=0.6,
                    max_rmse_m=0.5, max_correction_m=4.0, max_correction_deg=20.0, max_conflict=0.06,
                    free_space_margin_m=0.3)
        base.update(overrides)
        return cls(**base)


@dataclass(frozen=True)
class FrontEndConfig:
    """Front-end parameters. `FrontEndConfig()` suits the depth camera, `FrontEndConfig.lidar()` the LiDAR.

    odometry, loops:            see OdometryConfig and LoopConfig
    keyframe_every:             a keyframe needs at least this many frames since the last keyframe ...
    keyframe_min_translation_m, keyframe_min_rotation_deg: ... and this much motion since it (either one;
                                0 = that one unused; both 0 = every `keyframe_every`-th frame is a keyframe)
    loop_cooldown:              after an accepted loop, this many keyframes skip the loop search
    graph_max_corr_m:           pose-graph line-process distance (see PoseGraph.optimize): a loop edge that
                                disagrees with the odometry by much more than this is pruned. None =
                                loops.max_correction_m, the largest correction a verified loop may make
    preference_loop_closure, edge_prune_threshold: passed to PoseGraph.optimize
    level_gain, level_reference_frames: each frame's rotation is turned by this fraction of its scan's
                                tilt against the up direction its vertical surfaces say (`jaxmap.slam.level`;
                                0 = off, the default here and the depth camera's: it reads the sensor's z as
                                the first guess of up; `lidar()`: 1.0), the up being the first frame's
                                facades', averaged with the next frames' (at most this many in all) while
                                its standard error is above 5 mdeg (a noisy sensor's)
    edge_information:           "isotropic" (default): each edge's information is ICP's made isotropic per
                                block (the rotation block and the translation block each replaced by its
                                mean eigenvalue times I, no cross terms; `isotropic_information`); "icp":
                                open3d's information as computed. Measured on the drifting 300-frame room
                                (every 6th frame, 0.002 z^2 depth noise, one loop): ATE 12.9 cm odometry,
                                13.3 cm with "icp", 5.9 cm with "isotropic" (`jaxmap bench slam --only drift`)
    """
    odometry: OdometryConfig = field(default_factory=OdometryConfig)
    loops: LoopConfig = field(default_factory=LoopConfig)
    keyframe_every: int = 1             # a keyframe needs at least this many frames since the last keyframe ...
    keyframe_min_translation_m: float = 0.0  # ... and this much translation (or the rotation below; 0 = unused, both 0 = none)
    keyframe_min_rotation_deg: float = 0.0  # ... or this much rotation since it
    loop_cooldown: int = 0              # after an accepted loop, this many keyframes skip the loop search
    graph_max_corr_m: float | None = None  # pose-graph line-process distance (m); null = loops.max_correction_m
    preference_loop_closure: float = 1.0  # open3d GlobalOptimizationOption.preference_loop_closure
    edge_prune_threshold: float = 0.25  # open3d: loop edges with a line-process weight below this are pruned
    edge_information: str = "isotropic"  # isotropic (ICP's, per block) | icp (open3d's, with cross terms)
    level_gain: float = 0.0             # fraction of each frame's tilt against the facades' up turned away (0 = off)
    level_reference_frames: int = 10    # the up: the first frame's facades, with the next ones' (at most this many) while noisy

    @classmethod
    def lidar(cls, **overrides) -> "FrontEndConfig":
        """Street-LiDAR settings (OdometryConfig.lidar(), LoopConfig.lidar(), a keyframe every 3.5 m); keywords
        override fields. At 10 Hz a car's scans are ~1 m apart: a keyframe at each of them would put the
        loop search's min_gap (8 keyframes) 8 m back, within its 10 m radius, and "close a loop" with the
        scan 8 back at every frame (a pose-graph optimisation and a remap each); every 3.5 m keeps ~16
        keyframes on the small city's 62 m loop, as its 15 frames 4.7 m apart were before issue 25."""
        base = dict(odometry=OdometryConfig.lidar(), loops=LoopConfig.lidar(), keyframe_min_translation_m=3.5,
                    level_gain=LIDAR_LEVEL_GAIN, level_reference_frames=LIDAR_LEVEL_REFERENCE_FRAMES)
        base.update(overrides)
        return cls(**base)


@dataclass(frozen=True)
class SlamConfig:
    """Root config of `jaxmap slam` (front end + transformable latent map)."""

    data: DataConfig = field(default_factory=lambda: ImtConfig().data)
    preprocess: PreprocessConfig = field(default_factory=lambda: ImtConfig().preprocess)
    map: LatentMapConfig = field(default_factory=LatentMapConfig)
    mesh: LatentMeshConfig = field(default_factory=LatentMeshConfig)
    eval: EvalConfig = field(default_factory=lambda: ImtConfig().eval)
    frontend: FrontEndConfig = field(default_factory=FrontEndConfig)
    external_poses: str = ""          # directory of pose snapshots replacing the front end ("" = our own)
    mesh_at_loops: bool = False       # write meshes before and after each loop closure (a whole-map mesh each: slow)
    n3_config: str = ""               # imt: also build an N3 map from the optimised poses with this config;
                                      # n3: the N3 map's config (its MapConfig; data and output come from here)
    map_kind: str = "imt"             # imt: the transformable latent map, remapped at loops; n3: the N3 map of
                                      # n3_config, mapped online at the tracked poses (docs/slam.md)
    n3_track: bool = True             # n3: refine each odometry pose by tracking the scan against the N3 map
    n3_track_min_valid: float = 0.8   # n3: adopt a tracked pose only when this fraction of the scan's points lies in
                                      # the map (where it is young, n3_track_min_seen keeps it out: docs/slam.md)
    n3_track_max_range_m: float = 0.0  # n3: track with the scan's points within this range only (0 = all)
    n3_track_points: int = 4096       # n3: ... a random subset of this many of them (one compile for any scan)
    n3_track_min_seen: int = 2        # n3: track with the points whose map voxel holds training pairs of at least
                                      # this many frames (a place seen by one frame is fitted, not yet known, and
                                      # pulls the pose down: docs/slam.md); fewer than half the points there: the
                                      # odometry pose is kept
    n3_track_young_rotation: bool = True  # n3: ... unless the map is young there (fewer than half settled): then
                                      # the rotation tracked with every point is taken, with the odometry's
                                      # position (a young map biases the position, not the tilt: docs/slam.md)
    n3_track_submap_min_frames: int = 3  # n3_loop submaps: a scan is tracked against a submap of at least this
                                      # many frames (a new one holds little: the one before it is tracked against
                                      # while it grows; that one, seen from ever farther, pulled the poses by
                                      # 0.3-2 cm a new submap with 10: docs/slam.md)
    n3_loop: str = "moved"            # n3: how the map follows a loop correction: submaps (the map is a chain of
                                      # submaps of n3_submap_m, each pass its own; a loop moves each as a rigid
                                      # body), rebuild (one grid, every frame again at the optimised poses),
                                      # moved (one grid, re-add the frames that moved, their old training pairs
                                      # removed), none (docs/slam.md)
    n3_loop_min_move_m: float = 0.02  # n3: a loop that moves no frame's position more than this leaves the map
                                      # as it is; moved re-adds the frames that moved more; submaps re-adds the
                                      # frames of the submap being mapped that moved more than this against it
    n3_loop_readd_iters: int = 0      # n3: training iterations of a frame re-added after a loop (moved, submaps);
                                      # 0: the map's train.iters, as a new frame (a re-add costs a frame's time)
    n3_loop_readd_per_frame: int = 1  # n3 moved (and submaps): frames a loop moved are re-added this many after each
                                      # of the next frames, largest move first (0: moved re-adds all at the loop,
                                      # a stall of the main thread; the last frame re-adds those left)
    n3_set: list = field(default_factory=list)  # overrides of n3_config's keys ("section.key=value"): with map_kind
                                      # n3 the map's settings are n3_config's, not this file's preprocess/map/
                                      # mesh/eval (`jaxmap slam --set n3.train.iters=20` appends one)
    n3_submap_m: float = 30.0         # n3_loop submaps: a new submap once the sensor has driven this far in the
                                      # current one (the N3 map's submaps.length_m, with submaps.revisit false)
    checkpoint_every: int = 50        # save the run (map, front end, scans) every this many frames, so that a
                                      # crash or kill -9 loses at most these (0: only at the end and on Ctrl-C)
    output: str = "runs/slam"           # run directory (`--out` overrides it)
    progress: bool = True             # tqdm progress bar

    def unused(self) -> dict[str, str]:
        """{key or section: why} of what a run with this map kind does not read (`jaxmap slam` refuses
        `--set` of them rather than ignore it)."""
        if self.map_kind == "n3":
            why = (f"with map_kind n3 the map's settings are those of n3_config ({self.n3_config}): set the key "
                   "there or as --set n3.<key>=<value> (e.g. --set n3.preprocess.veil_m=0.3)")
            return {**{k: why for k in ("preprocess", "map", "mesh", "eval")},
                    "mesh_at_loops": "mesh_at_loops meshes the imt map at loops; with map_kind n3 it is not used"}
        why = f"{{}} is read with map_kind n3 only (this run's map_kind is {self.map_kind})"
        out = {k: why.format(k) for k in ("n3_track", "n3_track_min_valid", "n3_track_max_range_m", "n3_track_min_seen",
                                            "n3_track_young_rotation", "n3_track_points", "n3_track_submap_min_frames",
                                            "n3_loop",
                                            "n3_loop_min_move_m", "n3_loop_readd_iters",
                                            "n3_loop_readd_per_frame", "n3_submap_m")}
        if not self.n3_config:
            out["n3_set"] = "n3_set sets keys of n3_config's N3 map, and this run has none (n3_config is empty)"
        return out

    def imt(self) -> ImtConfig:
        return ImtConfig(data=self.data, preprocess=self.preprocess, map=self.map, mesh=self.mesh, eval=self.eval,
                         output=self.output, progress=self.progress)
