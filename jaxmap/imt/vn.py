"""Vector-neuron (VN) layers and the rotation action on pytrees.

Conventions (used by every module of `jaxmap.imt`):

* A vector feature is an array `[..., C, 3]`: C channels, each a 3-vector stored as a *row*.
  A rotation `R` ([3,3], acting on column vectors as `x -> R x`) acts on a feature by
  `V -> V R^T` (every row rotated). All layers here are written so that
  `f(V R^T) == f(V) R^T` holds for every orthogonal `R` (rotations and reflections).
* Frames: the layers are frame-agnostic; whatever frame the input rows are in, the output rows are
  in the same frame.

Layers (flax.linen):

* `VNLinear(features)`: `V [..., C_in, 3] -> W V [..., C_out, 3]`, no bias (a bias would break
  equivariance).
* `VNLeakyReLU(negative_slope)`: per output channel c, a learned direction `k_c = U_c V`; the
  component of `v_c` along `-k_c` is removed (eq. 2 of the IMT paper / Deng et al. 2021), with the
  projection guarded by `|k|^2 + 1e-6`. `negative_slope=0` is the paper's setting.
* `vn_mean_pool(V, mask, axis)`: (masked) mean over a point axis, equivariant because linear.
* `invariant_features(F, q)`: the invariant layer: inner products between vector features
  (upper triangle of the Gram matrix `F F^T`), and, given a query vector `q`, `F q` and `|q|^2`.
  These are unchanged by `F -> F R^T, q -> R q` for every orthogonal `R`.

Rotation of pytrees, `rotate(tree, R)` (jaxlie's idea: the group acts on whatever pytree holds its
elements, by a tree map that dispatches on a mark): a leaf is a vector only if it is explicitly
marked, either

* as a field of a dataclass, with `vector_field()` / `jacobian_field()` (the latent fields of
  `LatentMap` and `VoxelBatch` are declared this way), or
* by wrapping an array in `Vec` (rows of 3-vectors, `[..., 3]`, rotated as `v -> v R^T`) or `Jac`
  (Jacobians `[..., 3, 3]` of a vector w.r.t. a translation, rotated as `J -> R J R^T`).

Plain arrays are never touched, even when their last axis happens to be 3 (voxel centres are
*points*; they are transformed by the full pose elsewhere, and counts or SDF values are scalars).
A tree with no marked leaf at all raises: rotating it would silently do nothing. `Vec` and `Jac`
are pytree nodes, so marked leaves pass through `jax.jit`, `vmap`, `tree_map` and orbax unchanged.
"""
from __future__ import annotations

import dataclasses
from typing import Any

import flax.linen as nn
import flax.struct
import jax
import jax.numpy as jnp
import numpy as np

from jaxmap.geometry import einsum, rotate_vectors

EPS = 1e-6  # guard of the projection in VNLeakyReLU, as in the reference implementation


# ---------------------------------------------------------------------------------------------
# Layers
# ---------------------------------------------------------------------------------------------


def _vn_init(key, shape, dtype=jnp.float32):
    """Weights [C_out, C_in] ~ N(0, 1/C_in): keeps feature norms O(1) through a VN stack."""
    return jax.random.normal(key, shape, dtype) / np.sqrt(shape[1])


class VNLinear(nn.Module):
    """Channel mixing without bias. `V [..., C_in, 3] -> [..., features, 3]`, `W` is `[features, C_in]`.

    channels_last: the features are stored transposed, `[..., 3, C]` (vectors as columns): the same
    function with the same parameters, but a plain matmul over the last axis (`x @ W^T`, one GEMM),
    which XLA:CPU runs ~2x faster than the contraction over a middle axis for the hundreds of thousands
    of (point, voxel) pairs of a frame (`encoder.Encoder.per_point` uses it)."""

    features: int
    channels_last: bool = False

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        w = self.param("kernel", _vn_init, (self.features, x.shape[-1 if self.channels_last else -2]))
        if self.channels_last:
            return x @ w.T
        return jnp.einsum("oc,...cd->...od", w, x)


class VNLeakyReLU(nn.Module):
    """Vector-neuron leaky ReLU. `V [..., C, 3] -> [..., C, 3]`.

    For each channel c: `k_c = U_c V` (learned direction, `U` is `[C, C]`, or `[1, C]` when
    `share_direction`), and
    `v'_c = v_c` if `<v_c, k_c> >= 0`, else `v_c - <v_c, k_c> / (|k_c|^2 + 1e-6) k_c`;
    the output is `slope * v + (1 - slope) * v'`. Equivariant because `<v, k>` and `|k|` are
    invariant and `k` rotates with `V`.
    """

    negative_slope: float = 0.0
    share_direction: bool = False
    channels_last: bool = False     # `[..., 3, C]` features, as `VNLinear`

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        c = x.shape[-1 if self.channels_last else -2]
        u = self.param("direction", _vn_init, (1 if self.share_direction else c, c))
        vec = -2 if self.channels_last else -1                     # the axis of the 3 components
        d = x @ u.T if self.channels_last else jnp.einsum("oc,...cd->...od", u, x)
        dot = jnp.sum(x * d, axis=vec, keepdims=True)
        d_norm_sq = jnp.sum(d * d, axis=vec, keepdims=True)
        projected = x - (dot / (d_norm_sq + EPS)) * d
        out = jnp.where(dot >= 0, x, projected)
        if self.negative_slope:
            out = self.negative_slope * x + (1.0 - self.negative_slope) * out
        return out


def vn_mean_pool(x: jax.Array, mask: jax.Array | None = None, axis: int = -3) -> jax.Array:
    """Mean over the point axis. `x [..., N, C, 3]`, `mask [..., N]` (bool or 0/1) -> `[..., C, 3]`.

    With a mask, only valid points count; an all-empty set gives zeros (not NaN).
    """
    if mask is None:
        return jnp.mean(x, axis=axis)
    axis = axis % x.ndim
    m = mask.astype(x.dtype)
    m = m.reshape(m.shape + (1,) * (x.ndim - 1 - axis))
    total = jnp.sum(x * m, axis=axis)
    count = jnp.sum(m, axis=axis)
    return total / jnp.maximum(count, 1.0)


def vn_inner(a: jax.Array, b: jax.Array) -> jax.Array:
    """Inner products between the channels of two features: `[..., Ca, 3], [..., Cb, 3] -> [..., Ca, Cb]`."""
    return jnp.einsum("...id,...jd->...ij", a, b)


def gram_upper(f: jax.Array) -> jax.Array:
    """Upper triangle (diagonal included) of `F F^T`: `[..., C, 3] -> [..., C (C + 1) / 2]`. Invariant."""
    c = f.shape[-2]
    iu, ju = np.triu_indices(c)
    return vn_inner(f, f)[..., iu, ju]


def invariant_features(f: jax.Array, q: jax.Array | None = None) -> tuple[jax.Array, jax.Array | None]:
    """The invariant layer: rotation-invariant scalars of a latent and (optionally) a query.

    f: `[..., C, 3]` latent (rows rotate as `F R^T`); q: `[..., 3]` query position in the same frame
    (rotates as `R q`); leading dims of `f` (without C, 3) and `q` broadcast.

    Returns `(g, s)`: `g [..., C (C+1)/2]`, the Gram upper triangle of F (depends on F only, so a
    decoder can compute its contribution once per voxel), and `s [..., C + 1]` = `[|q|^2, F q]`
    (None when q is None). Every entry is an inner product of vectors of the same frame, hence
    invariant under any orthogonal change of frame applied to both.
    """
    g = gram_upper(f)
    if q is None:
        return g, None
    fq = jnp.sum(f * q[..., None, :], axis=-1)
    qq = jnp.sum(q * q, axis=-1, keepdims=True)
    qq = jnp.broadcast_to(qq, fq.shape[:-1] + (1,))
    return g, jnp.concatenate([qq, fq], axis=-1)


# ---------------------------------------------------------------------------------------------
# Rotation of pytrees
# ---------------------------------------------------------------------------------------------


@flax.struct.dataclass
class Vec:
    """Marks an array `[..., 3]` of 3-vectors (rows) that rotate as `v -> v R^T`.

    Use for VN latents `[..., C, 3]`, normals, directions. Do not use for points (positions):
    those also translate, which `rotate` does not do.
    """

    value: Any


@flax.struct.dataclass
class Jac:
    """Marks an array `[..., 3, 3]` of Jacobians `J = d v / d t` of a vector v w.r.t. a translation t
    (rows: components of v, columns: components of t). Both sides live in the rotated frame, so
    `J -> R J R^T` (for a latent Jacobian `[..., C, 3, 3]` this is per channel).
    """

    value: Any


ROTATION = "rotation"   # dataclass field metadata key: "vec" or "jac"


def vector_field(**kwargs):
    """A dataclass field holding rows of 3-vectors `[..., 3]` (rotated as `v R^T` by `rotate`)."""
    return flax.struct.field(metadata={ROTATION: "vec"}, **kwargs)


def jacobian_field(**kwargs):
    """A dataclass field holding translation Jacobians `[..., 3, 3]` (rotated as `R J R^T`); may be None."""
    return flax.struct.field(metadata={ROTATION: "jac"}, **kwargs)


def _marks(x) -> dict:
    """{field name: "vec" | "jac"} of a dataclass instance (empty for anything else)."""
    if not dataclasses.is_dataclass(x) or isinstance(x, type):
        return {}
    return {f.name: f.metadata[ROTATION] for f in dataclasses.fields(x) if ROTATION in f.metadata}


def _is_marked(x) -> bool:
    return isinstance(x, (Vec, Jac)) or bool(_marks(x))


def rotate_jacobians(j: jax.Array, R: jax.Array) -> jax.Array:
    """Jacobians `[..., 3, 3]` rotated by `R [3,3]`: `R J R^T`."""
    R = jnp.asarray(R, dtype=j.dtype)
    return einsum("ab,...bc,dc->...ad", R, j, R)


def _rotate_leaf(kind: str, v, R):
    if v is None:
        return None, 0
    if kind == "vec":
        if v.shape[-1] != 3:
            raise ValueError(f"Vec leaf must have last axis 3, got shape {v.shape}")
        return rotate_vectors(jnp.asarray(R, v.dtype), v, xnp=jnp), 1
    if v.shape[-2:] != (3, 3):
        raise ValueError(f"Jac leaf must end in [3, 3], got shape {v.shape}")
    return rotate_jacobians(v, R), 1


def rotate(tree: Any, R: jax.Array) -> Any:
    """Apply the rotation `R [3,3]` to every marked leaf of a pytree and leave everything else as is.

    `Vec(v)` becomes `Vec(v R^T)`, `Jac(J)` becomes `Jac(R J R^T)`, and so do the `vector_field` /
    `jacobian_field` fields of dataclasses anywhere in the tree (a None field stays None); unmarked
    leaves (including arrays whose last axis is 3) are returned unchanged (same objects). Works inside
    `jit` and `vmap`. Raises ValueError when the tree holds no marked leaf.
    """
    found = [0]

    def act(x):
        if isinstance(x, (Vec, Jac)):
            v, n = _rotate_leaf("vec" if isinstance(x, Vec) else "jac", x.value, R)
            found[0] += n
            return type(x)(v)
        if not _marks(x):
            return x
        changes = {}
        for f in dataclasses.fields(x):
            kind = f.metadata.get(ROTATION)
            if kind is not None:
                changes[f.name], n = _rotate_leaf(kind, getattr(x, f.name), R)
                found[0] += n
            elif f.metadata.get("pytree_node", True):
                sub = getattr(x, f.name)
                if _has_marks(sub):
                    changes[f.name] = jax.tree_util.tree_map(act, sub, is_leaf=_is_marked)
        return dataclasses.replace(x, **changes)

    out = jax.tree_util.tree_map(act, tree, is_leaf=_is_marked)
    if not found[0]:
        raise ValueError("rotate: the tree has no Vec/Jac-marked leaf (nor a vector_field/jacobian_field), so a "
                         "rotation would leave it unchanged; mark the leaves that are vectors or Jacobians")
    return out


def _has_marks(tree) -> bool:
    return any(_is_marked(x) for x in jax.tree_util.tree_leaves(tree, is_leaf=_is_marked))
