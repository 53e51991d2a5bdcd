"""Pose graph over keyframes, optimised with open3d's robust global optimisation (Choi et al. 2015).

Convention of this wrapper: node i has the pose T_w_i ([4,4] float64, T_world_keyframe); an edge
(i, j, T_ij) says T_ij = T_w_i^-1 @ T_w_j, i.e. T_ij maps points of node j into the frame of node i
(what ICP returns with source = j, target = i).

open3d's convention (checked in its GlobalOptimization.cpp, and numerically in the tests): node poses
are T_world_node and `PoseGraphEdge(source, target, X)` has zero error when X = T_target^-1 @ T_source,
so X maps source points into the target frame. Our (i, j, T_ij) is therefore open3d's edge
(source = j, target = i, X = T_ij). Loop edges are "uncertain": open3d's line process down-weights
them and prunes those that disagree with the rest of the graph.
"""
from __future__ import annotations

import numpy as np

from jaxmap.geometry import orthonormalize, pose_change, se3_inverse
from jaxmap.slam.odometry_common import quiet_open3d


class PoseGraph:
    """A growing pose graph. Add nodes in order, odometry and loop edges, then `optimize()`."""

    def __init__(self):
        self.poses: list[np.ndarray] = []                 # T_w_i estimates, updated by optimize()
        self.edges: list[tuple[int, int, np.ndarray, np.ndarray, bool]] = []  # (i, j, T_ij, info, loop)
        self.loop_confidence: dict[int, float] = {}       # edge index -> line-process confidence

    def __len__(self) -> int:
        return len(self.poses)

    def add_node(self, pose) -> int:
        """Append a node with initial pose [4,4] T_world_node; returns its id."""
        self.poses.append(orthonormalize(np.array(pose, dtype=np.float64)))
        return len(self.poses) - 1

    def _add_edge(self, i, j, T_ij, information, loop):
        n = len(self.poses)
        if not (0 <= i < n and 0 <= j < n) or i == j:
            raise ValueError(f"pose graph edge ({i}, {j}): nodes must be distinct ids in [0, {n})")
        self.edges.append((int(i), int(j), orthonormalize(np.array(T_ij, dtype=np.float64)),
                           np.array(information, dtype=np.float64), bool(loop)))

    def add_odometry(self, i: int, j: int, T_ij, information) -> None:
        """Certain edge: T_ij ([4,4], maps node j's points into node i's frame), information [6,6]."""
        self._add_edge(i, j, T_ij, information, loop=False)

    def add_loop(self, i: int, j: int, T_ij, information) -> None:
        """Uncertain (loop-closure) edge; same convention as add_odometry. May be pruned by optimize()."""
        self._add_edge(i, j, T_ij, information, loop=True)

    def to_open3d(self):
        """The graph as an `o3d.pipelines.registration.PoseGraph` (see the module docstring)."""
        import open3d as o3d

        reg = o3d.pipelines.registration
        g = reg.PoseGraph()
        for T in self.poses:
            g.nodes.append(reg.PoseGraphNode(T))
        for i, j, T_ij, info, loop in self.edges:
            g.edges.append(reg.PoseGraphEdge(j, i, T_ij, info, uncertain=loop))
        return g

    def optimize(self, max_corr_m: float, edge_prune_threshold: float = 0.25, preference_loop_closure: float = 1.0,
                 reference_node: int = 0, max_iteration: int = 100) -> np.ndarray:
        """Optimise all node poses (Levenberg-Marquardt); returns and stores them, [K,4,4] float64.

        max_corr_m: the registration distance (m) the edges were built with; with preference_loop_closure
        it sets the line-process weight, i.e. how much disagreement a loop edge may have before it is
        down-weighted (roughly max_corr_m * sqrt(preference_loop_closure)). Loop edges whose confidence
        falls below edge_prune_threshold are pruned (recorded in `loop_confidence` as their confidence).
        reference_node stays fixed.
        """
        import open3d as o3d

        if len(self.poses) == 0:
            return np.zeros((0, 4, 4))
        reg = o3d.pipelines.registration
        g = self.to_open3d()
        option = reg.GlobalOptimizationOption(max_correspondence_distance=float(max_corr_m),
                                              edge_prune_threshold=float(edge_prune_threshold),
                                              preference_loop_closure=float(preference_loop_closure),
                                              reference_node=int(reference_node))
        criteria = reg.GlobalOptimizationConvergenceCriteria()
        criteria.max_iteration = int(max_iteration)
        with quiet_open3d():
            reg.global_optimization(g, reg.GlobalOptimizationLevenbergMarquardt(), criteria, option)
        self.poses = [orthonormalize(np.array(n.pose, dtype=np.float64)) for n in g.nodes]  # LM leaves ~1e-3 off SO(3)
        # Which loop edges survived: match the remaining uncertain edges by their node pair.
        kept = {(e.target_node_id, e.source_node_id): e.confidence for e in g.edges if e.uncertain}
        self.loop_confidence = {k: float(kept.get((i, j), 0.0))
                                for k, (i, j, _, _, loop) in enumerate(self.edges) if loop}
        return np.stack(self.poses)

    def edge_errors(self) -> list[tuple[float, float]]:
        """Per edge, (rotation error in radians, translation error in m) of T_ij vs the current poses."""
        out = []
        for i, j, T_ij, _, _ in self.edges:
            est = se3_inverse(self.poses[i]) @ self.poses[j]
            a, d = pose_change(T_ij, est)
            out.append((float(a), float(d)))
        return out
