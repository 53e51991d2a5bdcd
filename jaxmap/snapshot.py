"""Copies of a map's arrays that a background thread owns (a live mesh, a background save) while the
next frames map."""
from __future__ import annotations


def copy_arrays(tree):
    """A copy of every jax array leaf of a pytree (numpy and Python leaves kept as they are).

    For a `snapshot_fn`: a mapper that donates its state buffers to the next frame's update (N3's jitted
    step does) deletes the arrays a background mesh is still reading; copies taken between frames are
    the thread's own. The copies are made on the device, asynchronously, in the order of the calls."""
    import jax

    return jax.tree_util.tree_map(lambda x: x.copy() if isinstance(x, jax.Array) else x, tree)
