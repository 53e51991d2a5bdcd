"""Reconstruction metrics: the N3-Mapping / SHINE-Mapping evaluation protocol (docs/evaluation.md).

The default protocol ("shine") is a literal implementation of SHINE-Mapping's ``eval_mesh``
(``utils/eval_utils.py``) with its MaiCity settings, which N3-Mapping reports with; world frame, metres in,
centimetres / percent out:

1. GT points are restricted to the observed region: points farther than ``cull_distance_m`` from every
   observed scan point (of the mapped frames, inside the mapper's range crop) are dropped, and with
   ``eval_radius_m > 0`` those farther than that from every sensor position (:func:`cull_gt`).
2. The predicted mesh is cropped to the axis-aligned bounding box of the kept GT points with z grown by
   the down-sampling voxel (2 cm), as open3d's ``mesh.crop(AxisAlignedBoundingBox)``: a triangle is
   kept when its three vertices are inside the box (:func:`crop_mesh`). (x and y are grown by 2 cm too,
   where SHINE grows only z: see CROP_XY_GROW_M.)
3. The cropped mesh is sampled as open3d's ``sample_points_uniformly`` (``n_samples`` points, 10 M in
   SHINE; :func:`sample_points_uniformly`), and both point sets are voxel-down-sampled at 2 cm as open3d's
   ``voxel_down_sample`` (the mean of the points in each voxel; :func:`voxel_down_sample`).
4. Accuracy = mean distance from each predicted point to its nearest GT point over the predicted points
   closer than ``acc_truncation_m`` = 0.2 m (the others are dropped); Precision = % of those kept closer
   than the threshold. Completion = mean distance from each GT point to its nearest predicted point,
   distances >= ``comp_truncation_m`` = 2.0 m counted as 2.0 m (SHINE's ``nn_correspondance`` with
   ``ignore_outlier=False``); Completion ratio = % of GT points closer than the threshold.
   Chamfer-L1 = (Accuracy + Completion) / 2; F-score = 2 P R / (P + R) with R = completion ratio.
   The threshold is 10 cm outdoors (configs/city.yaml) and 5 cm indoors (the room configs).

Every metrics dict carries ``"protocol": "shine"``. :func:`protocol_floor` is the same protocol with the
GT mesh itself as the prediction: the best score the protocol can give on that data (the sampling
floor), printed beside every table. With per-point GT classes (``gt_points.ply`` of ``jaxmap synth``),
:func:`signed_error_by_class` gives the mean signed distance of the predicted surface to the GT surface
per class (negative = the surface sinks below / into the true one).

Nothing here measures accuracy against the GT *mesh*: its hidden and never-observed faces would absorb
misplaced surface. ``protocol="surface"`` (``jaxmap eval --protocol surface``) adds one exact
surface-to-surface figure as an extra field, ``completion_surface_cm``: each kept GT point's distance to
the predicted *mesh* (open3d's BVH distance, clamped at 2 m), which has no sampling floor.

Beside the protocol (it drops predicted points farther than 0.2 m from the GT, so floaters and ghost
surfaces are invisible to it) every metrics dict also has pred_far_share (% of the down-sampled predicted
points so dropped), precision_all and f_score_all (precision and F-score with every predicted point
counted, far ones as misses). When a sequence has moving objects (:mod:`jaxmap.moving`), the observed
region comes from static hits only and :func:`evaluate_mesh_file` adds ghost_area_m2: the predicted
surface (m^2, per kind) inside space only moving objects occupied, farther than 0.15 m from the static GT.

The package imports numpy at import time only (scipy, trimesh and open3d lazily), so it runs on
machines without open3d; open3d is only used for ``completion_surface_cm``.
"""

from jaxmap.metrics.protocol import (
    mesh_distance,
    cull_gt,
    crop_box,
    crop_mesh,
    sample_points_uniformly,
    voxel_down_sample,
    protocol_metrics,
    culled_or_fail,
    evaluate,
    load_mesh,
    sample_mesh,
    signed_error_by_class,
    mesh_arrays,
    evaluate_culled,
    evaluate_mesh,
    surface_fields,
    subdivide_mesh,
    protocol_floor,
    format_metrics,
    PROTOCOL,
    PROTOCOLS,
    METRIC_KEYS,
    DOWN_SAMPLE_M,
    ACC_TRUNCATION_M,
    COMP_TRUNCATION_M,
    N_SAMPLES,
    SIGNED_MAX_M,
    CROP_XY_GROW_M,
    FLOOR_MAX_EDGE_M,
    OBSERVED_VOXEL_M,
)
from jaxmap.metrics.sequence import (
    voxel_thin,
    observed_points_of,
    read_gt,
    evaluate_mesh_file,
    FLOOR_CACHE,
)

_load_mesh = load_mesh  # the name `jaxmap.bench.figures` imports

__all__ = [
    "mesh_distance",
    "cull_gt",
    "crop_box",
    "crop_mesh",
    "sample_points_uniformly",
    "voxel_down_sample",
    "protocol_metrics",
    "culled_or_fail",
    "evaluate",
    "load_mesh",
    "sample_mesh",
    "signed_error_by_class",
    "mesh_arrays",
    "evaluate_culled",
    "evaluate_mesh",
    "surface_fields",
    "subdivide_mesh",
    "protocol_floor",
    "format_metrics",
    "PROTOCOL",
    "PROTOCOLS",
    "METRIC_KEYS",
    "DOWN_SAMPLE_M",
    "ACC_TRUNCATION_M",
    "COMP_TRUNCATION_M",
    "N_SAMPLES",
    "SIGNED_MAX_M",
    "CROP_XY_GROW_M",
    "FLOOR_MAX_EDGE_M",
    "OBSERVED_VOXEL_M",
    "voxel_thin",
    "observed_points_of",
    "read_gt",
    "evaluate_mesh_file",
    "FLOOR_CACHE",
]
