"""Tracking against the implicit map (PIN-SLAM's idea, in JAX): refine a scan's pose by minimising the
SDF of its points in an N3 map over SE(3), starting from a guess (odometry, constant velocity).

    res = track_scan(mapper.static, mapper.state, points_s, T_guess)   # TrackResult
    if res.ok: T = res.pose

The solve is Levenberg-Marquardt on a 6-vector (omega, v), a left perturbation in the map frame with
the rotation about the sensor: R <- exp(omega) R, t <- t + v, so x_i = R p_i + t moves by
omega x (R p_i) + v. Residual r_i = sdf(x_i) for the points inside allocated voxels (the others weigh
0); its Jacobian is grad sdf(x_i) chained with that point Jacobian, [(R p_i) x g_i, g_i], the gradient
by one reverse pass through the field (`jaxmap.n3.loss.sdf_and_grad`). Geman-McClure IRLS weights
w = (k^2 / (k^2 + r^2))^2, the kernel scale k annealed from `kernel_start_m` down to `kernel_m` over the
first iterations (wide enough at first to pull a pose 0.5 m off in, tight at the end so that what the
map does not hold - cars that moved, new facades - does not bias the pose). A step is kept when it
lowers the robust cost (points outside the map count as the kernel's ceiling, so a step cannot win
by pushing points out of the map); else the damping grows. The field is only defined near what the map
saw (points farther than ~0.4 m from a surface fall outside its voxels and carry no gradient), so a
guess a metre off along a street, or turned 15 degrees at a corner, has nothing pulling it back: with
`search_m` > 0 the solve starts from the best of a grid of moves of the guess (shifts in map x, y within
+-search_m, turns about the sensor's vertical within +-search_yaw_deg: a ground vehicle's uncertain
directions), each judged by the robust cost of a subset of the points, then a second such grid as fine
as the first one's spacing around the best (`search_stages`), in the same program.
With `min_seen` > 1 (jaxmap slam's `n3_track_min_seen`) the solve weighs only the points whose leaf
voxel holds training pairs of at least that many frames: a map of one frame fits that frame's own rings
but not the road between them, where its field reads the true surface centimetres above its zero set, so
its points pulled each pose down (1.2 cm from the first frame's map, docs/slam.md), and a map built at
those poses stays low; a pose tracked on fewer than `min_settled_fraction` of the points is not ok.
All iterations run in one jitted program
(`lax.while_loop`, stopping early on a small step) on a fixed number of points (`max_points`: a
scan is subsampled or padded to it), so the program compiles once per map shape.

`refine_pose` is the pure core, for any SDF (`sdf_fn(x [M, 3]) -> (sdf [M], valid [M])`), usable in
other jitted code; `track_scan` is the host wrapper for an N3 map: world <-> map frame in float64
(the map frame's origin is subtracted on the host, so float32 stays precise far from the world
origin), subsampling, and the verdict `ok`.
"""
from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxmap.geometry import einsum, matmul, orthonormalize
from jaxmap.n3 import window
from jaxmap.n3.query import QueryStatic, query, voxel_rows
from jaxmap.n3.state import N3State, N3Static, origin_world


@dataclass(frozen=True)
class TrackOptions:
    """How `track_scan` solves and judges (hashable: a static argument of the program)."""

    iterations: int = 30               # at most this many LM iterations (fewer once a step is tiny)
    kernel_m: float = 0.1              # Geman-McClure scale k at the end, metres
    kernel_start_m: float = 0.8        # ... at the first iteration, shrunk by `kernel_decay` per iteration
    kernel_decay: float = 0.75
    max_points: int = 4096             # scan points used (a random subset, or padding): one compile
    damping: float = 1e-3              # initial LM damping (times diag(H))
    min_valid_fraction: float = 0.8    # ok needs at least this fraction of the points inside the map
    max_rms_m: float = 0.06            # ... and their RMS SDF (each clipped at `rms_clip_m`) at most this
    rms_clip_m: float = 1.0
    step_tol_m: float = 1e-3           # converged: a step below this (translation, and rotation x 10 m)
    seed: int = 0                      # of the subsample
    search_m: float = 0.0              # > 0: first try a grid of horizontal shifts within +-search_m (see below),
    search_steps: int = 5              # ... search_steps x search_steps of them (map x, y)
    search_yaw_deg: float = 20.0       # ... each also turned about the vertical within +-search_yaw_deg
    search_yaw_steps: int = 9          # ... in this many steps
    search_points: int = 512           # ... each judged on this many of the points
    search_kernel_m: float = 0.3       # ... by the Geman-McClure cost at this scale
    search_stages: int = 2             # ... then again around the best, the grid shrunk to its spacing
    min_seen: int = 0                  # > 1: the solve weighs (and compares poses on) only the points whose leaf
                                       # voxel holds pairs of at least this many frames (`track_program`; 1: every
                                       # point, the test compiled in, so that a later min_seen > 1 compiles nothing)
    min_settled_fraction: float = 0.5  # ... and then ok needs at least this fraction of the points there


class TrackResult(NamedTuple):
    pose: np.ndarray        # [4, 4] float64 T_world_sensor, refined (the guess when nothing could be done)
    ok: bool                # enough points in the map, small RMS, converged
    valid_fraction: float   # of the used points, inside allocated voxels at the final pose
    rms_m: float            # RMS SDF of those points at the final pose (each clipped at rms_clip_m)
    iterations: int         # LM iterations run
    settled_fraction: float = 1.0  # of the used points, in voxels of at least `min_seen` frames at the final pose


class Refined(NamedTuple):
    """What `refine_pose` returns (device arrays)."""

    R: jax.Array            # [3, 3] map-frame rotation
    t: jax.Array            # [3] map-frame translation
    valid_fraction: jax.Array
    rms_m: jax.Array
    iterations: jax.Array
    converged: jax.Array    # the last step was below step_tol_m (at the final kernel scale)
    settled_fraction: jax.Array  # of the used points, inside the map where it is settled (sdf_fn's `settled`)


def so3_exp(w):
    """Rotation matrix [3, 3] of an axis-angle vector w [3] (Rodrigues, safe at 0)."""
    th2 = jnp.sum(w * w)
    small = th2 < 1e-8
    th = jnp.sqrt(jnp.where(small, 1.0, th2))
    a = jnp.where(small, 1.0 - th2 / 6.0, jnp.sin(th) / th)
    b = jnp.where(small, 0.5 - th2 / 24.0, (1.0 - jnp.cos(th)) / jnp.where(small, 1.0, th2))
    K = jnp.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]], w.dtype)
    return jnp.eye(3, dtype=w.dtype) + a * K + b * matmul(K, K)


def gm_weight(r, k):
    """Geman-McClure IRLS weight of residuals r at scale k."""
    k2 = k * k
    return (k2 / (k2 + r * r)) ** 2


def gm_cost(r, valid, mask, k):
    """Mean Geman-McClure cost rho(r) = (r^2 / 2) k^2 / (k^2 + r^2) over `mask`; a point outside the map
    (not `valid`) costs the ceiling k^2 / 2."""
    k2 = k * k
    rho = jnp.where(valid, 0.5 * r * r * k2 / (k2 + r * r), 0.5 * k2)
    return jnp.sum(jnp.where(mask, rho, 0.0)) / jnp.maximum(jnp.sum(mask), 1)


def _residuals(sdf_fn, points, R, t, grad: bool):
    """(r [M], valid [M], d r / d x [M, 3] or None, settled [M]) at x = R p + t (`_split`: what sdf_fn
    says is settled, all points when it says nothing)."""
    x = matmul(points, R.T) + t
    if not grad:
        r, (valid, settled) = _split(sdf_fn(x))
        return jnp.where(jnp.isfinite(r), r, 0.0), valid & jnp.isfinite(r), None, settled
    r, vjp, aux = jax.vjp(lambda p: _split(sdf_fn(p)), x, has_aux=True)
    valid, settled = aux
    (g,) = vjp(jnp.ones_like(r))
    finite = jnp.isfinite(r) & jnp.all(jnp.isfinite(g), axis=1)   # a NaN gradient would poison H
    g = jnp.where(finite[:, None], g, 0.0)
    return jnp.where(finite, r, 0.0), valid & finite, g, settled


def _split(out):
    """sdf_fn's (sdf, valid) or (sdf, (valid, settled)) -> (sdf, (valid, settled))."""
    r, aux = out
    return (r, aux) if isinstance(aux, tuple) else (r, (aux, jnp.ones_like(aux)))


def _lm_step(sdf_fn, points, mask, opts: TrackOptions, carry):
    """One LM iteration: carry (i, R, t, lam, converged, `_residuals` at (R, t)) -> the next. The residuals of
    the pose held are carried, so each iteration evaluates the field (and its gradient) once, at the step tried."""
    i, R, t, lam, _, (r, valid, g, settled) = carry
    k = jnp.maximum(opts.kernel_m, opts.kernel_start_m * opts.kernel_decay ** i.astype(jnp.float32))
    w = jnp.where(mask & valid & settled, gm_weight(r, k), 0.0)
    J = jnp.concatenate([jnp.cross(matmul(points, R.T), g), g], axis=1)   # [M, 6]: d r / d (omega, v)
    H = matmul((J * w[:, None]).T, J)
    b = matmul(J.T, w * r)
    A = H + lam * (jnp.diag(jnp.diag(H)) + 1e-6 * jnp.eye(6))
    delta = -jnp.linalg.solve(A, b)
    delta = jnp.where(jnp.all(jnp.isfinite(delta)), delta, 0.0)
    R2, t2 = matmul(so3_exp(delta[:3]), R), t + delta[3:]
    tried = _residuals(sdf_fn, points, R2, t2, grad=True)
    # the two poses compared on the points settled at both (a point that leaves the settled part is neither a
    # reward nor a penalty: it is still inside the map); points outside the map cost the ceiling
    both = mask & settled & tried[3]
    better = gm_cost(tried[0], tried[1], both, k) <= gm_cost(r, valid, both, k)
    small = jnp.maximum(jnp.linalg.norm(delta[3:]), 10.0 * jnp.linalg.norm(delta[:3])) < opts.step_tol_m
    R, t = jnp.where(better, R2, R), jnp.where(better, t2, t)
    held = jax.tree_util.tree_map(lambda a, b_: jnp.where(better, a, b_), tried, (r, valid, g, settled))
    lam = jnp.where(better, jnp.maximum(lam / 3.0, 1e-7), lam * 4.0)
    # converged: a tiny step (kept or not: at the optimum float32 noise decides) once the kernel is at its
    # final scale, or damping so large that nothing moves
    done = (small & (k <= opts.kernel_m * 1.0001)) | (lam > 1e6)
    return i + 1, R, t, lam, done, held


def search_grid(opts: TrackOptions) -> tuple[np.ndarray, np.ndarray]:
    """(shifts [S, 3] in units of search_m, yaws [S] in units of search_yaw_deg) of the search, the
    smallest moves first (the guess itself wins a tie)."""
    u = np.linspace(-1.0, 1.0, opts.search_steps)
    a = np.linspace(-1.0, 1.0, opts.search_yaw_steps) if opts.search_yaw_steps > 1 else np.zeros(1)
    gy, gx, ga = np.meshgrid(u, u, a, indexing="ij")
    shifts = np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], 1)
    order = np.lexsort((np.linalg.norm(shifts, axis=1), np.abs(ga.ravel())))
    return shifts[order].astype(np.float32), ga.ravel()[order].astype(np.float32)


def grid_search(sdf_fn, points_s, mask, R, t, search, opts: TrackOptions):
    """(R, t) turned about the sensor's vertical and shifted by the grid's move (`search_grid` scaled by
    search = (half-width m, yaw half-width rad)) whose robust cost on the first `search_points` points is lowest."""
    k = min(opts.search_points, points_s.shape[0])
    shifts, yaws = (jnp.asarray(g) for g in search_grid(opts))
    shifts, yaws = shifts * search[0], yaws * search[1]
    Rs = jax.vmap(lambda y: matmul(so3_exp(jnp.array([0.0, 0.0, 1.0]) * y), R))(yaws)    # [S, 3, 3]
    x = einsum("sij,kj->ski", Rs, points_s[:k]) + (t + shifts)[:, None]
    r, (valid, _) = _split(sdf_fn(x.reshape(-1, 3)))
    r, valid = r.reshape(len(yaws), k), valid.reshape(len(yaws), k)
    finite = jnp.isfinite(r)
    cost = jax.vmap(gm_cost, in_axes=(0, 0, None, None))(jnp.where(finite, r, 0.0), valid & finite, mask[:k],
                                                          opts.search_kernel_m)
    best = jnp.argmin(cost)
    return Rs[best], t + shifts[best]


def staged_search(sdf_fn, points_s, mask, R, t, search, opts: TrackOptions):
    """`grid_search` `search_stages` times, each between the grid points of the one before."""
    shrink = jnp.array([1.0 / max(opts.search_steps - 1, 1), 1.0 / max(opts.search_yaw_steps - 1, 1)])
    for _ in range(opts.search_stages):
        R, t = grid_search(sdf_fn, points_s, mask, R, t, search, opts)
        search = search * shrink
    return R, t


def refine_pose(sdf_fn, points_s, mask, R0, t0, opts: TrackOptions = TrackOptions(), search=None) -> Refined:
    """Pure LM refinement of T = (R0, t0) so that sdf_fn(R p + t) ~ 0 for the `mask`ed points.

    sdf_fn: map-frame points [M, 3] -> (sdf [M], valid [M] bool), differentiable in the points;
    points_s [M, 3] float32 sensor frame, in random order (the search uses the first rows); mask [M] bool
    (padding False); R0 [3, 3], t0 [3] map frame. search: the search's widths, [2] (half-width m, yaw
    half-width rad; may be traced; a half-width of 0 skips the search), or None: opts'; the search is
    compiled in when opts.search_m > 0."""
    points_s = jnp.asarray(points_s, jnp.float32)
    R0, t0 = jnp.asarray(R0, jnp.float32), jnp.asarray(t0, jnp.float32)
    if opts.search_m > 0:
        if search is None:
            search = jnp.array([opts.search_m, np.deg2rad(opts.search_yaw_deg)], jnp.float32)
        R0, t0 = jax.lax.cond(search[0] > 0, functools.partial(staged_search, sdf_fn, points_s, mask, opts=opts),
                              lambda R, t, s: (R, t), R0, t0, search)
    step = functools.partial(_lm_step, sdf_fn, points_s, mask, opts)
    held = _residuals(sdf_fn, points_s, R0, t0, grad=True)
    init = (jnp.int32(0), R0, t0, jnp.float32(opts.damping), jnp.bool_(False), held)
    i, R, t, _, done, _ = jax.lax.while_loop(lambda c: (c[0] < opts.iterations) & ~c[4], step, init)
    r, valid, _, settled = _residuals(sdf_fn, points_s, R, t, grad=False)
    inside = mask & valid
    n_in = jnp.sum(inside)
    rc = jnp.minimum(jnp.abs(r), opts.rms_clip_m)
    rms = jnp.sqrt(jnp.sum(jnp.where(inside, rc * rc, 0.0)) / jnp.maximum(n_in, 1))
    return Refined(R, t, n_in / jnp.maximum(jnp.sum(mask), 1), jnp.where(n_in > 0, rms, jnp.inf), i, done,
                   jnp.sum(inside & settled) / jnp.maximum(jnp.sum(mask), 1))


@functools.partial(jax.jit, static_argnums=(0, 1))
def track_program(static: QueryStatic, opts: TrackOptions, state: N3State, points_s, mask, R0, t0, search,
                  min_seen) -> Refined:
    """`refine_pose` against the N3 map (state) in its map frame: one compiled program per (static, opts)
    (static: what the query reads of the map's N3Static, so maps that differ only in training share it)
    (the search's widths are the traced `search`; a half-width of 0 skips it). With opts.min_seen >= 1 the
    settled test is compiled in and `min_seen` (traced int32) is its bar, <= 1: every point settled (so the
    tracker's two calls in `jaxmap slam`, the settled points' and every point's, share one program)."""
    def sdf_fn(x):
        sdf, valid = query(static, state, x)
        if opts.min_seen < 1:
            return sdf, valid
        bar = jnp.where(min_seen <= 1, jnp.iinfo(jnp.int32).min, min_seen)
        return sdf, (valid, frames_seen(static, state, x) >= bar)

    return refine_pose(sdf_fn, points_s, mask, R0, t0, opts, search)


def frames_seen(static: N3Static | QueryStatic, state: N3State, points_m):
    """[N] int32: frames that gave training pairs to the leaf voxel of each map-frame point [N, 3] (0: none).
    A finished submap keeps no pair store (`jaxmap.n3.submaps`): every point of it counts as seen enough."""
    if state.store is None:
        return jnp.full(points_m.shape[:1], jnp.iinfo(jnp.int32).max, jnp.int32)
    slot = window.block_of(state.store, voxel_rows(static, state, points_m))
    return jnp.where(slot >= 0, state.store.frames_seen[jnp.maximum(slot, 0)], 0)


def subsample(points_s, n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(points [n, 3] float32, mask [n] bool): a random subset of n rows of points_s [N, 3] (or all of
    them, padded with zero rows, mask False), in random order."""
    pts = np.asarray(points_s, np.float32).reshape(-1, 3)
    pts = pts[np.random.default_rng(seed).permutation(len(pts))[:n]]
    out = np.zeros((n, 3), np.float32)
    out[:len(pts)] = pts
    return out, np.arange(n) < len(pts)


def track_scan(static: N3Static, state: N3State, points_s, T_init, opts: TrackOptions = TrackOptions()) -> TrackResult:
    """Refine T_init ([4, 4] T_world_sensor) so that the scan points_s ([N, 3] sensor frame, already
    cropped / downsampled) lie on the map's zero level set. See the module docstring."""
    T_init = np.asarray(T_init, np.float64)
    pts, mask = subsample(points_s, opts.max_points, opts.seed)
    if not mask.any():
        return TrackResult(T_init.copy(), False, 0.0, float("inf"), 0)
    origin = origin_world(static, state)
    t0 = (T_init[:3, 3] - origin).astype(np.float32)
    # one compile for any widths (and none), and one for any min_seen >= 1 (traced)
    flags = dataclasses.replace(opts, search_m=1.0, search_yaw_deg=0.0, min_seen=min(opts.min_seen, 1))
    widths = np.array([max(opts.search_m, 0.0), np.deg2rad(opts.search_yaw_deg)], np.float32)
    out = jax.device_get(track_program(QueryStatic.of(static), flags, state, pts, mask, T_init[:3, :3].astype(np.float32), t0,
                                       widths, np.int32(opts.min_seen)))
    pose = np.eye(4)
    pose[:3, :3] = np.asarray(out.R, np.float64)
    pose[:3, 3] = np.asarray(out.t, np.float64) + origin
    pose = orthonormalize(pose)
    vf, rms, sf = float(out.valid_fraction), float(out.rms_m), float(out.settled_fraction)
    settled = opts.min_seen <= 1 or sf >= opts.min_settled_fraction
    ok = bool(out.converged) and vf >= opts.min_valid_fraction and rms <= opts.max_rms_m and settled
    return TrackResult(pose, ok, vf, rms, int(out.iterations), sf)
