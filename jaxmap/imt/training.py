"""Training and evaluation of the equivariant prior (`jaxmap prior`, `jaxmap.commands.prior`).

`jaxmap prior train [prior] [--out RUN] [--set k=v ...]` trains the encoder and decoder
(CNP-style: the encoder sees a voxel's surface points and normals, the decoder predicts the SDF at
query points) on `jaxmap.synth.shapes` patches and writes to the run directory:
`config.yaml` (resolved), `prior.npz` (weights + model config + figures), `metrics.json`,
`history.json`, `loss.png`, and orbax checkpoints under `checkpoints/` (resumed with
`--set train.resume=true`). `export` in the config also copies the weights (e.g. to the package).

`jaxmap prior eval [config] [--out RUN]` prints validation figures (NLL, mean |SDF error| near the
surface, held-out plane / sphere / box-corner patches) for the shipped weights, or for RUN's.

Loss (as DI-Fusion / IMT): Gaussian NLL of the clamped label under N(clamped mean, std),
`0.5 ((clip(mu) - clip(y)) / std)^2 + log std + 0.5 log 2 pi`, averaged over queries, plus
`latent_reg * mean |F|^2`. Point noise (Gaussian) and normal noise (tilt by a random angle) are
drawn afresh every step.
"""
from __future__ import annotations

import json
import logging
import math
import os
import time

import jax
import jax.numpy as jnp
import numpy as np
import optax
from tqdm import tqdm

from jaxmap.config import save_config
from jaxmap.config.prior import PriorConfig, PriorDataConfig, PriorTrainConfig
from jaxmap.imt.prior import WEIGHTS_FILE, Prior, count_params, init_prior, save_prior
from jaxmap.synth.shapes import HELDOUT_PATCHES, KINDS, PatchSpec, heldout_patches, make_dataset

log = logging.getLogger("jaxmap")


# ---------------------------------------------------------------------------------------------
# Loss, noise, evaluation
# ---------------------------------------------------------------------------------------------


def perturb(key, points, normals, point_noise: float, normal_noise_deg: float):
    """Gaussian point noise (std `point_noise`) and normals tilted by an angle uniform in
    `[0, normal_noise_deg]` degrees towards a random tangent direction. Shapes `[..., 3]` kept."""
    k1, k2, k3 = jax.random.split(key, 3)
    points = points + point_noise * jax.random.normal(k1, points.shape, points.dtype)
    g = jax.random.normal(k2, normals.shape, normals.dtype)
    u = g - jnp.sum(g * normals, axis=-1, keepdims=True) * normals
    u = u / (jnp.linalg.norm(u, axis=-1, keepdims=True) + 1e-9)
    ang = jax.random.uniform(k3, normals.shape[:-1] + (1,), normals.dtype) * math.radians(normal_noise_deg)
    normals = jnp.cos(ang) * normals + jnp.sin(ang) * u
    return points, normals


def gaussian_nll(mean, std, y, clamp: float):
    """Per-query NLL of clip(y) under N(clip(mean), std) (clip to +-clamp)."""
    r = (jnp.clip(mean, -clamp, clamp) - jnp.clip(y, -clamp, clamp)) / std
    return 0.5 * r * r + jnp.log(std) + 0.5 * math.log(2.0 * math.pi)


def _forward(prior: Prior, batch: dict, points, normals):
    f, _ = prior.encode(points, normals, batch["mask"])
    mean, std = prior.decode(f[:, None], batch["queries"])
    return f, mean, std


def make_loss(cfg: PriorConfig):
    dcfg, tcfg = cfg.data, cfg.train

    def loss_fn(params, model_cfg, batch, key):
        prior = Prior(params, model_cfg)
        pts, nrm = perturb(key, batch["points"], batch["normals"], dcfg.point_noise, dcfg.normal_noise_deg)
        f, mean, std = _forward(prior, batch, pts, nrm)
        nll = jnp.mean(gaussian_nll(mean, std, batch["sdf"], tcfg.clamp))
        reg = jnp.mean(jnp.sum(f * f, axis=(-2, -1)))
        return nll + tcfg.latent_reg * reg, nll

    return loss_fn


def batch_metrics(prior: Prior, batch: dict, key, clamp: float, point_noise: float = 0.0,
                  normal_noise_deg: float = 0.0) -> dict:
    """Per-voxel sums `[B]` (divide by the counts): NLL over all queries, |error| and std over the
    queries within 0.5 voxel of the surface. Inputs are perturbed when a noise level is non-zero."""
    pts, nrm = batch["points"], batch["normals"]
    if point_noise or normal_noise_deg:
        pts, nrm = perturb(key, pts, nrm, point_noise, normal_noise_deg)
    _, mean, std = _forward(prior, batch, pts, nrm)
    y = batch["sdf"]
    near = (jnp.abs(y) < 0.5).astype(mean.dtype)
    return {
        "nll_sum": jnp.sum(gaussian_nll(mean, std, y, clamp), axis=-1),
        "n": jnp.full(y.shape[:1], y.shape[-1], mean.dtype),
        "abs_near_sum": jnp.sum(jnp.abs(mean - y) * near, axis=-1),
        "n_near": jnp.sum(near, axis=-1),
        "std_near_sum": jnp.sum(std * near, axis=-1),
    }


_batch_metrics_jit = jax.jit(batch_metrics, static_argnames=("clamp", "point_noise", "normal_noise_deg"))


def _summarise(sums: dict, sel) -> dict:
    t = {k: float(np.sum(v[sel])) for k, v in sums.items()}
    return {
        "nll": t["nll_sum"] / max(t["n"], 1.0),
        "mae_near": t["abs_near_sum"] / max(t["n_near"], 1.0),
        "std_near": t["std_near_sum"] / max(t["n_near"], 1.0),
    }


def evaluate(prior: Prior, data: dict, cfg: PriorConfig, noisy: bool = True, chunk: int = 250, seed: int = 7,
             by_kind: bool = False) -> dict:
    """NLL, mean |SDF error| for |sdf| < 0.5 voxel and mean predicted std there, over a whole set.

    `noisy`: inputs perturbed with the training noise of `cfg.data` (fixed keys, reproducible);
    otherwise clean. NLL uses `cfg.train.clamp`; the |error| is not clamped. The last chunk is
    padded (one compiled shape). With `by_kind`, also `{"by_kind": {kind: {...}}}` per primary
    primitive of the scene (`data["kind"]`).
    """
    noise = (cfg.data.point_noise, cfg.data.normal_noise_deg) if noisy else (0.0, 0.0)
    keys = ("points", "normals", "mask", "queries", "sdf")
    n = len(data["sdf"])
    chunk = min(chunk, n)
    parts: dict = {}
    for i, s in enumerate(range(0, n, chunk)):
        idx = np.minimum(np.arange(s, s + chunk), n - 1)  # pad by repeating the last voxel
        b = {k: jnp.asarray(data[k][idx]) for k in keys}
        m = _batch_metrics_jit(prior, b, jax.random.PRNGKey(seed + i), clamp=cfg.train.clamp,
                               point_noise=noise[0], normal_noise_deg=noise[1])
        valid = min(chunk, n - s)
        for k, v in m.items():
            parts.setdefault(k, []).append(np.asarray(v)[:valid])
    sums = {k: np.concatenate(v) for k, v in parts.items()}
    out = _summarise(sums, slice(None))
    if by_kind and "kind" in data:
        out["by_kind"] = {KINDS[k]: _summarise(sums, data["kind"] == k) for k in np.unique(data["kind"])}
    return out


def evaluate_patches(prior: Prior, cfg: PriorConfig, n: int = 16, seed: int = 12345) -> dict:
    """Mean |SDF error| within 0.5 voxel of the surface on the held-out clean patches, queries
    in the voxel's cell (`inner`) and in the whole 2x neighbourhood (`cube`)."""
    out = {}
    for name in HELDOUT_PATCHES:
        for where, inner in (("inner", True), ("cube", False)):
            data = heldout_patches(name, n=n, seed=seed, n_points=cfg.data.n_points, inner=inner)
            out[f"{name}_{where}"] = evaluate(prior, data, cfg, noisy=False)["mae_near"]
    return out


# ---------------------------------------------------------------------------------------------
# Training
# ---------------------------------------------------------------------------------------------


def _patch_spec(d: PriorDataConfig):
    return PatchSpec(n_points=d.n_points, min_points=d.min_points, n_queries=d.n_queries,
                     near_frac=d.near_frac, near_sigma=d.near_sigma)


def make_val_set(cfg: PriorConfig) -> dict:
    """The validation voxels of `cfg.data` (seed + 1000003: disjoint from training)."""
    d = cfg.data
    return make_dataset(d.n_val, d.seed + 1000003, _patch_spec(d), union_prob=d.union_prob)


def make_datasets(cfg: PriorConfig, progress: bool = False) -> tuple[dict, dict]:
    """(training, validation) voxel sets of `cfg.data` (dicts of arrays, see `shapes.make_dataset`)."""
    d = cfg.data
    spec = _patch_spec(d)
    bar = None
    if progress:
        bar = tqdm(total=d.n_train + d.n_val, desc="prior data", unit="vox", leave=False)
    upd = bar.update if bar is not None else None
    train = make_dataset(d.n_train, d.seed, spec, union_prob=d.union_prob, progress=upd)
    val = make_dataset(d.n_val, d.seed + 1000003, spec, union_prob=d.union_prob, progress=upd)
    if bar is not None:
        bar.close()
    return train, val


def make_optimizer(cfg: PriorTrainConfig):
    sched = optax.warmup_cosine_decay_schedule(0.0, cfg.lr, cfg.warmup, max(cfg.steps, cfg.warmup + 1),
                                               end_value=cfg.lr_final)
    return optax.chain(optax.clip_by_global_norm(cfg.grad_clip), optax.adam(sched))


def _plot_history(history: list[dict], path: str) -> None:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:  # matplotlib is a dev extra; the run is still complete without the plot
        log.warning("matplotlib not installed; skipping %s", path)
        return
    tr = [h for h in history if "train_nll" in h]
    va = [h for h in history if "val_nll" in h]
    fig, ax = plt.subplots(1, 2, figsize=(10, 4))
    ax[0].plot([h["step"] for h in tr], [h["train_nll"] for h in tr], label="train NLL (running mean)")
    ax[0].plot([h["step"] for h in va], [h["val_nll"] for h in va], "o-", label="validation NLL")
    ax[0].set_xlabel("step")
    ax[0].set_ylabel("Gaussian NLL (voxel units)")
    ax[0].legend()
    ax[1].plot([h["step"] for h in va], [h["val_mae_near"] for h in va], "o-", label="validation |err|, |sdf|<0.5")
    ax[1].set_xlabel("step")
    ax[1].set_ylabel("mean |SDF error| (voxels)")
    ax[1].set_yscale("log")
    ax[1].legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _restore(mngr, state: dict, hist_path: str, resume: bool) -> tuple[dict, list]:
    """(state, history) of the latest checkpoint when resuming, else as given."""
    history: list[dict] = []
    if resume and mngr.latest_step() is not None:
        import orbax.checkpoint as ocp  # heavy: only a training run needs it

        state = mngr.restore(mngr.latest_step(), args=ocp.args.StandardRestore(state))
        if os.path.isfile(hist_path):
            with open(hist_path) as f:
                history = [h for h in json.load(f) if h["step"] <= int(state["step"])]
        log.info("prior: resumed from step %d", int(state["step"]))
    return state, history


def make_step(cfg: PriorConfig, opt):
    """The jitted training step `(state, batch, base_key) -> (state, loss, nll)`."""
    loss_fn = make_loss(cfg)
    model_cfg = cfg.model

    @jax.jit
    def step_fn(state, batch, base_key):
        key = jax.random.fold_in(base_key, state["step"])  # noise key: a function of the step
        (loss, nll), grads = jax.value_and_grad(loss_fn, has_aux=True)(state["params"], model_cfg, batch, key)
        updates, opt_state = opt.update(grads, state["opt_state"], state["params"])
        params = optax.apply_updates(state["params"], updates)
        return {"params": params, "opt_state": opt_state, "step": state["step"] + 1}, loss, nll

    return step_fn


_BATCH_KEYS = ("points", "normals", "mask", "queries", "sdf")


def _train_loop(cfg: PriorConfig, state: dict, history: list, train_set: dict, val_set: dict, key, mngr,
                hist_path: str, t_start: float) -> dict:
    """Steps from `state["step"]` to `cfg.train.steps`, with validation, history and checkpoints."""
    import orbax.checkpoint as ocp  # heavy: only a training run needs it

    tcfg = cfg.train
    step_fn = make_step(cfg, make_optimizer(tcfg))
    n_train = len(train_set["sdf"])
    rng = np.random.default_rng(tcfg.seed + int(state["step"]))
    start = int(state["step"])
    run_nll, run_n = 0.0, 0
    bar = tqdm(range(start, tcfg.steps), desc="prior train", unit="step", disable=not tcfg.progress,
               initial=start, total=tcfg.steps)
    for step in bar:
        idx = rng.integers(0, n_train, tcfg.batch_size)
        state, _, nll = step_fn(state, {k: jnp.asarray(train_set[k][idx]) for k in _BATCH_KEYS}, key)
        run_nll, run_n, s = run_nll + float(nll), run_n + 1, step + 1
        if s % 50 == 0 or s == tcfg.steps:
            history.append({"step": s, "train_nll": run_nll / run_n, "time_s": time.time() - t_start})
            bar.set_postfix(nll=f"{run_nll / run_n:.3f}")
            run_nll, run_n = 0.0, 0
        if s % tcfg.val_every == 0 or s == tcfg.steps:
            m = evaluate(Prior(state["params"], cfg.model), val_set, cfg)
            history.append({"step": s, "val_nll": m["nll"], "val_mae_near": m["mae_near"],
                            "val_std_near": m["std_near"], "time_s": time.time() - t_start})
            log.info("prior: step %d  val NLL %.4f  |err| near surface %.4f voxel", s, m["nll"], m["mae_near"])
        if s % tcfg.ckpt_every == 0 or s == tcfg.steps:
            mngr.save(s, args=ocp.args.StandardSave(state))
            with open(hist_path, "w") as f:
                json.dump(history, f)
    bar.close()
    mngr.wait_until_finished()
    return state


def summary_of(prior: Prior, cfg: PriorConfig, val_set: dict, times: dict) -> dict:
    """Validation figures of a trained prior (noisy, clean, held-out patches, per kind) and its sizes."""
    val = evaluate(prior, val_set, cfg, by_kind=True)
    val_clean = evaluate(prior, val_set, cfg, noisy=False)
    return {
        **times,
        "val_nll": val["nll"], "val_mae_near": val["mae_near"], "val_std_near": val["std_near"],
        "val_clean_nll": val_clean["nll"], "val_clean_mae_near": val_clean["mae_near"],
        "patch_mae_near": evaluate_patches(prior, cfg),
        "val_mae_near_by_kind": {k: v["mae_near"] for k, v in val["by_kind"].items()},
        "params_encoder": count_params(prior.params["encoder"]),
        "params_decoder": count_params(prior.params["decoder"]),
    }


def train(cfg: PriorConfig, out_dir: str) -> dict:
    """Train a prior; write the run directory; return the summary dict (also in metrics.json)."""
    import orbax.checkpoint as ocp  # heavy: only a training run needs it

    logging.getLogger("absl").setLevel(logging.WARNING)  # orbax logs every save at INFO
    t_start = time.time()
    os.makedirs(out_dir, exist_ok=True)
    save_config(cfg, os.path.join(out_dir, "config.yaml"))
    train_set, val_set = make_datasets(cfg, progress=cfg.train.progress)
    t_data = time.time() - t_start
    log.info("prior: %d training / %d validation voxels generated in %.1f s", len(train_set["sdf"]),
             len(val_set["sdf"]), t_data)
    key, k_init = jax.random.split(jax.random.PRNGKey(cfg.train.seed))
    prior = init_prior(cfg.model, k_init)
    state = {"params": prior.params, "opt_state": make_optimizer(cfg.train).init(prior.params),
             "step": jnp.asarray(0, jnp.int32)}
    mngr = ocp.CheckpointManager(os.path.abspath(os.path.join(out_dir, "checkpoints")),
                                 options=ocp.CheckpointManagerOptions(max_to_keep=2, create=True))
    hist_path = os.path.join(out_dir, "history.json")
    state, history = _restore(mngr, state, hist_path, cfg.train.resume)
    t_train0 = time.time()
    state = _train_loop(cfg, state, history, train_set, val_set, key, mngr, hist_path, t_start)
    times = {"data_time_s": round(t_data, 1), "train_time_s": round(time.time() - t_train0, 1)}
    prior = Prior(state["params"], cfg.model)
    summary = {"steps": cfg.train.steps, **summary_of(prior, cfg, val_set, times)}
    summary["total_time_s"] = round(time.time() - t_start, 1)
    summary["weights_bytes"] = save_prior(prior, os.path.join(out_dir, WEIGHTS_FILE), meta=summary)
    if cfg.export:
        save_prior(prior, cfg.export, meta=summary)
        summary["exported_to"] = cfg.export
    with open(hist_path, "w") as f:
        json.dump(history, f)
    with open(os.path.join(out_dir, "metrics.json"), "w") as f:
        json.dump(summary, f, indent=2)
    _plot_history(history, os.path.join(out_dir, "loss.png"))
    return summary
