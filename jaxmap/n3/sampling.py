"""Training-pair sampling: near-surface samples with SDF labels, and free-space samples.

Label modes (N3 paper, section III-B1; `sampling.label_mode`):
  normal      x = p + d n, label d            (non-projective; exact on planes)          [N3 default]
  projective  x = p - d r, label d            (distance along the ray; over-estimates at grazing angles)
  corrected   x = p - d r, label d |cos(r,n)| (projective distance projected on the normal)
with d ~ N(0, sigma) clipped to [-tr, tr], n the unit normal oriented towards the sensor, r the unit
ray direction sensor -> p. Signs: the SDF is positive in front of the surface (towards the sensor).

Free-space samples lie on the ray between the sensor and the truncation band, of two kinds:
  band  `free_sample_n` per point, uniform in the last `free_band_m` metres before the band (where
        the field must turn positive just outside the surface);
  ray   `free_ray_n` per point, stratified along the whole ray from `free_min_range_m` to the band
        (the paper: "along the ray between the sensor and the truncation region", which "eliminates
        potential artifacts caused by dynamic objects"): a car that drove through the space in front
        of the sensor left surface pairs in voxels that later rays cross, and only samples spread
        over the whole ray reach them.
Samples that land in voxels without features carry no feature gradient and are dropped (counted) by
the mapper; all others are kept wherever they land. Their label (`sampling.free_label_mode`):
  projected   min(tr, (|p - o| - t) |r . n|): the sample's distance to the tangent plane of its own
              hit point. Exact on planes and never above the true distance to a convex surface seen
              from outside; at grazing angles (a ray a metre before the road passes centimetres above
              it) it is centimetres, where a flat label would claim tr.                      [default]
  truncation  tr (or `free_label_m`) for every free sample, the paper's rule (ablation): it lies about
              free samples near grazing surfaces and pushes the road and sidewalks down.
"""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

LABEL_MODES = ("normal", "projective", "corrected")
FREE_LABEL_MODES = ("projected", "truncation")


class Samples(NamedTuple):
    """A frame's training pairs, flattened: S = N * (n_surface + n_free)."""

    points: jax.Array    # [S,3] float32, map frame
    labels: jax.Array    # [S] float32, metres
    surface: jax.Array   # [S] bool, inside the truncation band (gets the eikonal term)
    valid: jax.Array     # [S] bool, False for padding


def sample_frame(key, points_m, normals_m, valid, origin_m, *, label_mode: str, trunc: float, sigma: float,
                 n_surface: int, n_free: int, free_band: float, free_label: float,
                 free_label_mode: str = "projected", n_ray: int = 0, min_range: float = 0.0) -> Samples:
    """Sample training pairs for one frame (jit-able; everything after `origin_m` is static).

    points_m: [N,3] float32 map frame; normals_m: [N,3] unit, oriented towards the sensor;
    valid: [N] bool (padding mask); origin_m: [3] sensor position in the map frame.
    Per point: n_surface near-surface samples, then n_free band samples, then n_ray samples along the
    whole ray (from min_range metres to the band), so S = N * (n_surface + n_free + n_ray).
    """
    if label_mode not in LABEL_MODES:
        raise ValueError(f"sampling.label_mode must be one of {LABEL_MODES}, got {label_mode!r}")
    if free_label_mode not in FREE_LABEL_MODES:
        raise ValueError(f"sampling.free_label_mode must be one of {FREE_LABEL_MODES}, got {free_label_mode!r}")
    k_surf, k_free = jax.random.split(key)
    k_ray = jax.random.fold_in(k_free, 1)  # (not a 3-way split: the other two draws stay as they were)
    n = points_m.shape[0]
    ray = points_m - origin_m
    dist = jnp.linalg.norm(ray, axis=-1, keepdims=True)       # [N,1]
    r = ray / jnp.maximum(dist, 1e-6)                          # [N,3] unit, sensor -> p
    cos = jnp.abs(jnp.sum(r * normals_m, axis=-1, keepdims=True))   # [N,1] |cos| of the incidence angle

    d = jnp.clip(sigma * jax.random.normal(k_surf, (n, n_surface)), -trunc, trunc)   # [N,ns]
    if label_mode == "normal":
        xs = points_m[:, None] + d[..., None] * normals_m[:, None]
        ls = d
    else:
        xs = points_m[:, None] - d[..., None] * r[:, None]
        ls = d
        if label_mode == "corrected":
            ls = d * cos

    # Free space: uniform in [dist - trunc - free_band, dist - trunc], never behind the sensor.
    u = jax.random.uniform(k_free, (n, n_free))
    far = jnp.maximum(dist - trunc, 0.0)
    near = jnp.maximum(far - free_band, 0.0)
    t = near + u * (far - near)                                # [N,nf]
    # Along the whole ray: one sample in each of n_ray equal strata of [min_range, far] (stratified,
    # so every stretch of every ray is visited, however few samples a ray gets).
    start = jnp.minimum(min_range, far)
    strata = (jnp.arange(n_ray, dtype=jnp.float32) + jax.random.uniform(k_ray, (n, n_ray))) / max(n_ray, 1)
    t = jnp.concatenate([t, start + strata * (far - start)], axis=1)   # [N,nf+nr]
    xf = origin_m + t[..., None] * r[:, None]
    lf = jnp.full((n, n_free + n_ray), free_label, jnp.float32)
    if free_label_mode == "projected":
        lf = jnp.minimum(lf, (dist - t) * cos)

    pts = jnp.concatenate([xs, xf], axis=1).reshape(-1, 3)
    labels = jnp.concatenate([ls, lf], axis=1).reshape(-1)
    surface = jnp.concatenate([jnp.ones((n, n_surface), bool), jnp.zeros((n, n_free + n_ray), bool)],
                              1).reshape(-1)
    v = jnp.repeat(valid, n_surface + n_free + n_ray)
    return Samples(pts.astype(jnp.float32), labels.astype(jnp.float32), surface, v)
