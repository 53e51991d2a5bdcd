"""The config of `jaxmap prior` (configs/prior.yaml mirrors this tree): the equivariant encoder and the
invariant decoder of the transformable map's prior, its synthetic training data and its training."""
from __future__ import annotations

from dataclasses import dataclass, field


@dataclass(frozen=True)
class EncoderConfig:
    hidden: int = 32            # channels of the two hidden VN layers of each branch
    latent: int = 9             # channels of each branch's output; latent is [2 * latent, 3]
    negative_slope: float = 0.0  # VNLeakyReLU slope (the paper uses 0)
    inputs: str = "joint"       # "joint": each branch sees [p, n]; "split": p and n separately (paper)

    def __post_init__(self):
        if self.inputs not in ("joint", "split"):
            raise ValueError(f"encoder inputs must be 'joint' or 'split', got {self.inputs!r}")


@dataclass(frozen=True)
class LatentDecoderConfig:
    hidden: int = 128       # width of the MLP
    layers: int = 3         # hidden layers (the first is the split invariant layer)
    min_std: float = 1e-3   # floor of the predicted standard deviation (voxel units)


@dataclass(frozen=True)
class PriorModelConfig:
    encoder: EncoderConfig = field(default_factory=EncoderConfig)
    decoder: LatentDecoderConfig = field(default_factory=LatentDecoderConfig)


@dataclass(frozen=True)
class PriorDataConfig:
    n_train: int = 32000          # training voxels (generated once, noise redrawn every step)
    n_val: int = 2000             # validation voxels (other seed)
    n_points: int = 64            # points per voxel (padded; valid count varies)
    min_points: int = 16          # smallest valid count
    n_queries: int = 128          # SDF queries per voxel
    near_frac: float = 0.8        # share of queries near the surface (rest uniform in the 2x cube)
    near_sigma: float = 0.25      # std of near-surface query offsets along the normal (voxels)
    union_prob: float = 0.35      # share of scenes that are unions of 2-3 primitives
    point_noise: float = 0.025    # std of point noise (voxels), as the paper's training
    normal_noise_deg: float = 40.0  # normals tilted by an angle uniform in [0, this] degrees
    seed: int = 0                 # training set seed; validation uses seed + 1000003


@dataclass(frozen=True)
class PriorTrainConfig:
    steps: int = 10000               # training steps
    batch_size: int = 32          # voxels per step
    lr: float = 2e-3              # Adam peak learning rate
    warmup: int = 200             # linear warm-up steps, then cosine decay
    lr_final: float = 2e-5           # learning rate at the end of the cosine decay
    clamp: float = 1.0            # labels and mean predictions clipped to +-clamp voxels in the NLL
    latent_reg: float = 1e-3      # weight of mean |F|^2
    grad_clip: float = 1.0        # global gradient-norm clip
    val_every: int = 500             # steps between validation passes
    ckpt_every: int = 1000           # steps between orbax checkpoints
    resume: bool = False          # continue from the latest checkpoint of the run directory
    progress: bool = True         # tqdm progress bar
    seed: int = 0                 # parameter init and noise


@dataclass(frozen=True)
class PriorConfig:
    """Root config of `jaxmap prior`."""

    model: PriorModelConfig = field(default_factory=PriorModelConfig)
    data: PriorDataConfig = field(default_factory=PriorDataConfig)
    train: PriorTrainConfig = field(default_factory=PriorTrainConfig)
    output: str = "runs/prior"       # run directory (`--out` overrides it)
    export: str = ""              # also write the trained weights to this path ("" = don't)
