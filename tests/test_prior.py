"""The shipped prior, its training data and its command line.

The accuracy test decodes held-out synthetic patches (a plane, a sphere of radius 2 voxels, a
convex box corner; seeds never used in training) with the weights shipped in the package.
"""
from __future__ import annotations

import json
import os
import types

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxmap.config import ConfigError, load_config
from jaxmap.errors import JaxmapError
from jaxmap.geometry import random_rotation
from jaxmap.imt import Jac, Vec, load_prior, rotate
from jaxmap.config import PriorConfig
from jaxmap.imt.prior import init_prior, save_prior, shipped_weights_path
from jaxmap.commands import prior as prior_command
from jaxmap.imt.training import evaluate_patches
from jaxmap.synth import shapes

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
CONFIG = os.path.join(REPO, "configs", "prior.yaml")


@pytest.fixture(scope="module")
def prior():
    return load_prior()


# --------------------------------------------------------------------------------------------
# Shipped weights
# --------------------------------------------------------------------------------------------


def test_shipped_weights_small_and_complete(prior):
    size = os.path.getsize(shipped_weights_path())
    assert size < 1_000_000
    _, meta = load_prior(with_meta=True)
    assert meta["steps"] > 0 and "val_nll" in meta
    assert prior.latent_channels == 18


def test_shipped_prior_decodes_heldout_patches(prior):
    """Mean |SDF error| within 0.5 voxel of the surface <= 0.1 voxel on each held-out patch kind,
    queries in the voxel's own cell (what mesh extraction decodes)."""
    cfg = PriorConfig()
    mae = evaluate_patches(prior, cfg, n=16, seed=424242)
    for name in shapes.HELDOUT_PATCHES:
        assert mae[f"{name}_inner"] <= 0.1, (name, mae)
    # the whole 2x neighbourhood is harder (the surface may leave it) but still close
    assert max(mae[f"{n}_cube"] for n in shapes.HELDOUT_PATCHES) <= 0.2, mae


def test_shipped_prior_end_to_end_rotation(prior):
    """Trained weights: encode(P R^T, N R^T) == encode(P, N) R^T (1e-5), J -> R J R^T, and the
    decoded SDF of rotated inputs at rotated queries is unchanged (1e-5)."""
    data = shapes.heldout_patches("sphere_r2", n=4, seed=99, n_queries=64)
    p, n, q = (jnp.asarray(data[k]) for k in ("points", "normals", "queries"))
    R = jnp.asarray(random_rotation(np.random.default_rng(3)), jnp.float32)
    f, J, count = jax.jit(prior.encode_with_jacobian)(p, n)
    f_r, J_r, _ = jax.jit(prior.encode_with_jacobian)(p @ R.T, n @ R.T)
    scale = max(1.0, float(jnp.max(jnp.abs(f))))
    assert float(jnp.max(jnp.abs(f_r - f @ R.T))) < 1e-5 * scale
    rotated = rotate({"F": Vec(f), "J": Jac(J), "count": count}, R)
    assert float(jnp.max(jnp.abs(J_r - rotated["J"].value))) < 1e-4 * max(1.0, float(jnp.max(jnp.abs(J))))
    np.testing.assert_array_equal(rotated["count"], count)
    mu, sd = prior.decode(f[:, None], q)
    mu_r, sd_r = prior.decode(f_r[:, None], q @ R.T)
    np.testing.assert_allclose(mu_r, mu, atol=1e-5)
    np.testing.assert_allclose(sd_r, sd, atol=1e-5)
    assert bool(jnp.all(sd > 0))


def test_save_load_roundtrip(tmp_path):
    p0 = init_prior(PriorConfig().model, jax.random.PRNGKey(1))
    path = tmp_path / "w.npz"
    save_prior(p0, path, meta={"steps": 0})
    p1, meta = load_prior(path, with_meta=True)
    assert meta == {"steps": 0} and p1.cfg == p0.cfg
    for a, b in zip(jax.tree_util.tree_leaves(p0.params), jax.tree_util.tree_leaves(p1.params)):
        np.testing.assert_array_equal(a, b)
    with pytest.raises(JaxmapError, match="prior train"):
        load_prior(tmp_path / "missing.npz")


# --------------------------------------------------------------------------------------------
# Config
# --------------------------------------------------------------------------------------------


def test_config_file_matches_schema():
    """configs/prior.yaml spells out every key of PriorConfig with its default value."""
    import dataclasses

    import yaml

    cfg = load_config(CONFIG, schema=PriorConfig)
    assert cfg == PriorConfig()

    def keys(d, prefix=""):
        out = set()
        for k, v in d.items():
            out |= keys(v, f"{prefix}{k}.") if isinstance(v, dict) else {prefix + k}
        return out

    def schema_keys(c, prefix=""):
        out = set()
        for f in dataclasses.fields(c):
            v = getattr(c, f.name)
            out |= schema_keys(v, f"{prefix}{f.name}.") if dataclasses.is_dataclass(v) else {prefix + f.name}
        return out

    with open(CONFIG) as f:
        assert keys(yaml.safe_load(f)) == schema_keys(cfg)
    cfg = load_config(CONFIG, ["train.steps=7", "model.encoder.inputs=split"], schema=PriorConfig)
    assert cfg.train.steps == 7 and cfg.model.encoder.inputs == "split"
    with pytest.raises(ConfigError, match="did you mean 'train.steps'"):
        load_config(CONFIG, ["train.stepz=7"], schema=PriorConfig)


# --------------------------------------------------------------------------------------------
# Synthetic shapes
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("kind", shapes.KINDS)
def test_primitive_sdfs_are_exact(kind):
    """An exact SDF has |grad| = 1 and one projection step x - d grad(d) lands on the surface."""
    rng = np.random.default_rng(shapes.KINDS.index(kind))
    for _ in range(3):
        scene = shapes.Scene([shapes.random_primitive(rng, kind)])
        x = scene.prims[0].anchor(rng, 400) + rng.normal(0.0, 0.3, (400, 3))
        d = scene.sdf(x)
        g = scene.grad(x)
        gn = np.linalg.norm(g, axis=1)
        smooth = np.abs(gn - 1.0) < 1e-4  # away from creases/medial axis (measure zero)
        assert smooth.mean() > 0.9
        y = x[smooth] - d[smooth, None] * g[smooth]
        assert np.abs(scene.sdf(y)).max() < 1e-6


def test_dataset_layout_and_determinism():
    spec = shapes.PatchSpec(n_points=32, min_points=8, n_queries=16)
    a = shapes.make_dataset(40, seed=5, spec=spec)
    b = shapes.make_dataset(40, seed=5, spec=spec)
    for k in a:
        np.testing.assert_array_equal(a[k], b[k])
    assert a["points"].shape == (40, 32, 3) and a["queries"].shape == (40, 16, 3) and a["sdf"].shape == (40, 16)
    assert np.abs(a["points"]).max() <= 1.0 + 1e-6 and np.abs(a["queries"]).max() <= 1.0
    np.testing.assert_allclose(np.linalg.norm(a["normals"], axis=-1), 1.0, atol=1e-5)
    counts = a["mask"].sum(axis=1)
    assert counts.min() >= 8 and counts.max() <= 32
    assert np.mean(np.abs(a["sdf"]) < 0.5) > 0.5  # most queries near the surface


def test_heldout_patch_labels():
    d = shapes.heldout_patches("sphere_r2", n=3, seed=1, n_points=32, n_queries=64)
    assert np.abs(d["queries"]).max() <= 0.5
    # points lie on a sphere of radius 2 whose outward normals point away from its centre
    p, n = d["points"][0].astype(np.float64), d["normals"][0].astype(np.float64)
    c = p - 2.0 * n
    np.testing.assert_allclose(c, np.broadcast_to(c.mean(0), c.shape), atol=1e-4)
    q = d["queries"][0]
    np.testing.assert_allclose(d["sdf"][0], np.linalg.norm(q - c.mean(0), axis=1) - 2.0, atol=1e-4)


# --------------------------------------------------------------------------------------------
# Command line
# --------------------------------------------------------------------------------------------


def test_cli_train_resume_and_eval(tmp_path, capsys):
    out = str(tmp_path / "run")
    small = ["data.n_train=64", "data.n_val=16", "data.n_queries=32", "data.n_points=32",
             "train.batch_size=4", "train.val_every=2", "train.ckpt_every=2", "train.progress=false"]
    args = types.SimpleNamespace(action="train", config=CONFIG, out=out, data=None,
                                 overrides=small + ["train.steps=2"])
    assert prior_command(args) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    for f in ("prior.npz", "metrics.json", "history.json", "loss.png", "config.yaml"):
        assert os.path.isfile(os.path.join(out, f)), f
    assert os.path.isdir(os.path.join(out, "checkpoints", "2"))
    assert summary["steps"] == 2 and np.isfinite(summary["val_nll"])
    # resume continues from the checkpoint at step 2
    args.overrides = small + ["train.steps=4", "train.resume=true"]
    assert prior_command(args) == 0
    hist = json.load(open(os.path.join(out, "history.json")))
    assert [h["step"] for h in hist if "val_nll" in h] == [2, 4]
    capsys.readouterr()
    ev = types.SimpleNamespace(action="eval", config=CONFIG, out=out, data=None,
                               overrides=["data.n_val=16", "data.n_queries=32", "data.n_points=32"])
    assert prior_command(ev) == 0
    res = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert res["weights"].endswith("prior.npz") and np.isfinite(res["val_nll"])
    assert set(res["patch_mae_near"]) == {f"{n}_{w}" for n in shapes.HELDOUT_PATCHES for w in ("inner", "cube")}
