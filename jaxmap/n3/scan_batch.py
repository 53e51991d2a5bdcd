"""The scan as a frame program takes it: a preprocessed `ScanBatch` in the map frame, or a `RawScan`
in the sensor frame that the program preprocesses itself (`preprocess.device`), both padded to a
bucket of rows (`jaxmap.sizes.bucket_for`); `jaxmap.n3.scan` builds them on the host.
"""
from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxmap.geometry import SE3
from jaxmap.n3.state import N3Static
from jaxmap.preprocess_device import crop_mask, preprocess_scan, voxel_keep
from jaxmap.range_image import min_range_image_jax, veil_keep


class ScanBatch(NamedTuple):
    """One preprocessed scan in the map frame, padded to a bucket size N, and (free-space evidence on) the
    whole scan's range image with the sensor's rotation."""

    points: jax.Array    # [N, 3] float32 map frame
    normals: jax.Array   # [N, 3] float32 unit, oriented towards the sensor
    valid: jax.Array     # [N] bool, False for padding
    sensor: jax.Array    # [3] float32 sensor position, map frame
    rotation: jax.Array | None = None  # [3, 3] float32 R_map_sensor
    image: jax.Array | None = None     # [H, W] float32 nearest return per pixel (inf: none), `range_image`


class RawScan(NamedTuple):
    """One raw scan in the sensor frame, padded to a bucket size N, and its pose in the map frame
    (`preprocess.device`: the frame program crops, downsamples and estimates normals itself)."""

    points: jax.Array       # [N, 3] float32 sensor frame
    valid: jax.Array        # [N] bool, False for padding
    rotation: jax.Array     # [3, 3] float32 R_map_sensor
    translation: jax.Array  # [3] float32 sensor position, map frame


def preprocess_raw(static: N3Static, raw: RawScan, rows: int) -> tuple[ScanBatch, jax.Array, jax.Array]:
    """Crop, downsample and normals of a raw scan (`jaxmap.preprocess_device`), its kept points in
    their input order moved to the map frame and packed into `rows` rows (padding as `scan.to_batch`).
    Returns (ScanBatch [rows], points kept [] int32, overflow [] bool: more kept points than rows)."""
    cfg = static.preprocess
    raw_valid = raw.valid
    if cfg.veil_m > 0 and static.image is None:  # the host reads it off the scan; a traced program cannot
        raise ValueError("preprocess.veil_m on the device needs the scans' range-image layout: resolve it "
                         "first (jaxmap.n3.scan.resolve_layout), or set preprocess.veil_m: 0")
    # one range image a scan, of every return: the veil reads it, and the veil's returns still block the
    # free-space test (`scan.preprocess`)
    image = min_range_image_jax(raw.points, raw.valid, static.image) if (static.evidence or cfg.veil_m > 0) else None
    if cfg.veil_m > 0:
        raw_valid = raw_valid & veil_keep(raw.points, static.image, cfg.veil_m, valid=raw_valid, xp=jnp, image=image)
    image = image if static.evidence else None
    pts_s, nrm_s, valid, kept = preprocess_scan(raw.points, raw_valid, cfg, rows)
    T_m_s = SE3.from_rotation_and_translation(raw.rotation, raw.translation)  # (full float32 on a GPU: `geometry`)
    pts, nrm = T_m_s.apply(pts_s), T_m_s.rotation().apply(nrm_s)
    pts = jnp.where(valid[:, None], pts, raw.translation + 1.0)
    nrm = jnp.where(valid[:, None], nrm, np.array([0.0, 0.0, 1.0], np.float32))
    return (ScanBatch(pts, nrm, valid, raw.translation, raw.rotation if static.evidence else None, image), kept,
            kept > rows)


@functools.partial(jax.jit, static_argnums=0)
def count_kept(static: N3Static, raw: RawScan):
    """Points a raw scan keeps after crop and downsample (sizes the first frame's rows)."""
    p = static.preprocess
    keep = crop_mask(raw.points, raw.valid, min_range=p.min_range_m, max_range=p.max_range_m, min_z=p.min_z_m,
                     max_z=p.max_z_m)
    return jnp.sum(voxel_keep(raw.points, keep, p.vox_down_m), dtype=jnp.int32)

