"""Pictures for the README and docs/, made from run outputs (matplotlib, a dev dependency).

    python -m jaxmap.bench.figures ghost --data DATA --mesh LABEL=MESH [--mesh LABEL=MESH ...] --out PNG

`ghost`: a top view of each mesh on a sequence with moving objects, side by side: static ground truth
in light grey, the predicted surface in dark grey, and in red the ghost surface that
`jaxmap eval` measures (inside the space only moving objects occupied, > 0.15 m from the static GT).
"""
from __future__ import annotations

import argparse
import os

import numpy as np


def ghost_points(mesh_path: str, data_dir: str, n_samples: int = 2_000_000, seed: int = 0):
    """(surface samples [N,3], ghost mask [N] bool) of a mesh (world frame) on a sequence with moving
    objects: a sample is ghost where it lies in a moving object's box (grown as in the metric) and
    farther than the metric's static distance from every GT point."""
    from scipy.spatial import cKDTree

    from jaxmap import moving
    from jaxmap.metrics import load_mesh, read_gt, sample_points_uniformly

    objects = moving.load_moving_objects(data_dir)
    if objects is None:
        raise SystemExit(f"{data_dir} has no moving objects (moving_objects.json / pedestrians.json)")
    mesh = load_mesh(mesh_path)
    pts = sample_points_uniformly(np.asarray(mesh.vertices), np.asarray(mesh.faces), n_samples, seed)
    gt = read_gt(data_dir)["points"]
    inside = moving.inside_boxes(pts, objects.boxes, moving.GHOST_INFLATE_M)
    far = np.ones(len(pts), bool)
    if inside.any():
        d, _ = cKDTree(gt).query(pts[inside], k=1, distance_upper_bound=moving.GHOST_STATIC_M + 1e-6, workers=-1)
        far[inside] = d > moving.GHOST_STATIC_M
    return pts, inside & far


def ghost_figure(data_dir: str, meshes: dict, out_png: str, n_samples: int = 2_000_000) -> dict:
    """Write the side-by-side top views of `meshes` ({label: mesh path}) to out_png; returns
    {label: ghost share of the samples}."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from jaxmap.metrics import read_gt

    gt = read_gt(data_dir)["points"]
    gt = gt[np.random.default_rng(0).choice(len(gt), min(len(gt), 400_000), replace=False)]
    fig, axes = plt.subplots(1, len(meshes), figsize=(7 * len(meshes), 7), squeeze=False)
    shares = {}
    for ax, (label, path) in zip(axes[0], meshes.items()):
        pts, ghost = ghost_points(path, data_dir, n_samples)
        keep = pts[:, 2] > 0.3  # above the road and sidewalks: what stands (buildings, cars, ghosts)
        sub = np.random.default_rng(1).random(len(pts)) < 0.25
        ax.scatter(gt[gt[:, 2] > 0.3, 0], gt[gt[:, 2] > 0.3, 1], s=0.05, c="#d0d0d0", rasterized=True)
        m = keep & ~ghost & sub
        ax.scatter(pts[m, 0], pts[m, 1], s=0.05, c="#404040", rasterized=True)
        ax.scatter(pts[ghost, 0], pts[ghost, 1], s=0.3, c="#e02020", rasterized=True)
        shares[label] = float(ghost.mean())
        ax.set_title(f"{label}: ghost surface in red", fontsize=12)
        ax.set_aspect("equal")
        ax.set_xticks([])
        ax.set_yticks([])
    fig.tight_layout(rect=(0, 0, 1, 0.95))  # (room for the titles)
    os.makedirs(os.path.dirname(os.path.abspath(out_png)), exist_ok=True)
    fig.savefig(out_png, dpi=90)
    plt.close(fig)
    return shares


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m jaxmap.bench.figures")
    sub = p.add_subparsers(dest="figure", required=True)
    g = sub.add_parser("ghost", help="top views of meshes on a sequence with moving objects, ghosts in red")
    g.add_argument("--data", required=True)
    g.add_argument("--mesh", action="append", required=True, metavar="LABEL=PATH")
    g.add_argument("--out", required=True)
    args = p.parse_args(argv)
    meshes = dict(m.split("=", 1) for m in args.mesh)
    for path in meshes.values():
        if not os.path.isfile(path):
            raise SystemExit(f"mesh file not found: {path}")
    print(ghost_figure(args.data, meshes, args.out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
