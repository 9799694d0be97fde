"""Settings of the model-free baselines (`Config.baseline`, CLI keys `baseline.*`), with their sources.

The SAC learner's values are MEDAL's (docs/baselines.md, "The SAC learner"). R3L's classifier and RND
values are templates (MEDAL's discriminator, DI-engine's RND; docs/baselines.md, "R3L"), since MoReFree
does not state its own; where we had to choose, the field's comment says what and why. Importing it starts no
JAX backend (config.py imports it before the CLIs configure the runtime).
"""

from __future__ import annotations

import dataclasses

from morefree_jax.precision import check_precision

WEIGHT_INITS = ("xavier", "orthogonal")
ALPHA_UPDATES = ("adam", "clipped_step")


@dataclasses.dataclass(frozen=True)
class SACConfig:
    """docs/baselines.md, "The SAC learner" (MEDAL `cfgs/oracle.yaml`, `agents.py`); the defaults are MEDAL's.
    The options below them exist for IBC's variant (docs/baselines.md, "Learner" under "IBC"; `IBCConfig.sac`
    sets them):
    hidden_depth: ReLU layers per head; weight_init: xavier (uniform) or orthogonal, zero biases;
    log_std_squash: tanh then affine into [log_std_min, log_std_max] instead of a hard clip;
    critic_loss_weight: 0.5 (MEDAL) or 1 (IBC: MSE1 + MSE2); alpha_update: Adam on log alpha (MEDAL) or
    IBC's plain step alpha <- clip(alpha - alpha_step_size * mean(-log pi - target entropy), alpha_bounds);
    actor_update_every / target_update_every: the actor + alpha and the Polyak steps run on updates
    0, k, 2k, ...; target_entropy None: target_entropy_per_dim * |A| (MEDAL -|A|/2, IBC -|A|)."""

    feature_dim: int = 50
    hidden_dim: int = 256
    lr: float = 3e-4
    discount: float = 0.99
    tau: float = 0.005
    reward_scale: float = 10.0
    init_temperature: float = 1.0
    target_entropy: float | None = None
    log_std_min: float = -20.0
    log_std_max: float = 2.0
    batch_size: int = 256
    hidden_depth: int = 2
    weight_init: str = "xavier"
    log_std_squash: bool = False
    critic_loss_weight: float = 0.5
    alpha_update: str = "adam"
    alpha_step_size: float = 1e-5
    alpha_bounds: tuple[float, float] = (0.001, 0.5)
    actor_update_every: int = 1
    target_update_every: int = 1
    target_entropy_per_dim: float = -0.5
    precision: str = "f32"  # of the networks' matmuls: "f32" or "bf16" (morefree_jax/precision.py)

    def __post_init__(self):
        check_precision(self.precision)
        for name in ("feature_dim", "hidden_dim", "lr", "init_temperature", "batch_size", "hidden_depth",
                     "critic_loss_weight", "alpha_step_size", "actor_update_every", "target_update_every"):
            if getattr(self, name) <= 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        for name in ("discount", "tau"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"{name} must be in [0, 1], got {getattr(self, name)}")
        if self.weight_init not in WEIGHT_INITS:
            raise ValueError(f"unknown weight_init {self.weight_init!r}; valid: "
                             f"{', '.join(WEIGHT_INITS)}")
        if self.alpha_update not in ALPHA_UPDATES:
            raise ValueError(f"unknown alpha_update {self.alpha_update!r}; valid: "
                             f"{', '.join(ALPHA_UPDATES)}")
        if len(self.alpha_bounds) != 2 or not 0 < self.alpha_bounds[0] <= self.alpha_bounds[1]:
            raise ValueError(f"alpha_bounds must be (low, high) with 0 < low <= high, "
                             f"got {self.alpha_bounds}")
        if self.log_std_min >= self.log_std_max:
            raise ValueError(f"log_std_min must be < log_std_max, "
                             f"got {self.log_std_min} >= {self.log_std_max}")


@dataclasses.dataclass(frozen=True)
class ClassifierConfig:
    """R3L's VICE-style goal classifier, on MEDAL's discriminator template (docs/baselines.md, "R3L"):
    one hidden layer of 128 ReLU, BCE with mixup, 400 goal examples + 400 visited states per batch, Adam
    3e-4, one update every 10 env steps; reward -log(1 - sigmoid(D(s')) + eps)."""

    hidden: int = 128
    lr: float = 3e-4
    batch: int = 800
    train_every: int = 10
    mixup: bool = True
    eps: float = 1e-10

    def __post_init__(self):
        for name in ("hidden", "lr", "batch", "train_every", "eps"):
            if getattr(self, name) <= 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        if self.batch % 2:
            raise ValueError(f"batch must be even (goal examples and visited states), got {self.batch}")


@dataclasses.dataclass(frozen=True)
class RNDConfig:
    """R3L's backward (exploration) reward: random network distillation with DI-engine's settings
    (docs/baselines.md, "R3L"): target and predictor MLPs [64, 64, 128], predictor Adam 1e-3, batch 64,
    running mean/std whitening of observations, reward = per-sample squared error min-max normalised to
    [0, 1] within the batch ('assign' mode: the backward policy sees no other reward).

    Choices (MoReFree does not say): one predictor step per backward env step (DI-engine runs 100 per
    collection of unstated size); whitened observations clipped to [-5, 5] as the RND paper and DI-engine's
    hands-on notes do, not DI-engine's config default [-1, 1], under which every state beyond one standard
    deviation looks alike."""

    hidden: tuple[int, ...] = (64, 64, 128)
    lr: float = 1e-3
    batch: int = 64
    clip: float = 5.0

    def __post_init__(self):
        if not self.hidden or min(self.hidden) <= 0:
            raise ValueError(f"hidden must be positive widths, got {self.hidden}")
        for name in ("lr", "batch", "clip"):
            if getattr(self, name) <= 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")


def _ibc_sac() -> SACConfig:
    """docs/baselines.md, "Learner" under "IBC" (IBC `ibc.py`, `config_default.yaml`): 3 x 512 heads,
    orthogonal init, log-std tanh-squashed into [-10, 2], lr 1e-4, batch 512 (the forward agent takes half:
    IBCConfig), alpha0 0.5 with the clipped plain step, target entropy -|A|, actor and alpha every 2 updates,
    target every 2 with tau 0.01, loss MSE1 + MSE2, reward in {-1, 0} unscaled."""
    return SACConfig(hidden_dim=512, hidden_depth=3, weight_init="orthogonal", log_std_squash=True,
                     log_std_min=-10.0, log_std_max=2.0, lr=1e-4, batch_size=512, init_temperature=0.5,
                     alpha_update="clipped_step", target_entropy_per_dim=-1.0, actor_update_every=2,
                     target_update_every=2, tau=0.01, critic_loss_weight=1.0, reward_scale=1.0)


@dataclasses.dataclass(frozen=True)
class IBCConfig:
    """IBC (docs/baselines.md, "IBC"; its per-task values live in baselines/ibc/tasks.py).
    random_steps: uniform random actions first (`num_random_steps` 400); the seed phase without updates
    is run.prefill, which the ibc agent sets to `num_seed_steps` 800 (variants.py). her_relabel: share of
    each batch relabelled with a future achieved goal (`n_sampled_goal` 4 -> 4/5). pool_size: FIFO of
    forward trajectories (`pool_length` 1000); slots: curriculum goals (`num_episodes` 50); match_first /
    match_every: the matching runs at forward segment 5 and every 20 (`hgg_sampler_update_frequency`);
    cost_c / cost_l: HGG's c 3 and L 5; value_samples: actions averaged in a goal's value (10);
    goal_draws: curriculum draws of a goal the current state does not already reach (2); when all are
    reached a forward goal falls back to a task goal, a backward goal keeps the last draw (IBC's train.py).
    sac.batch_size: `rl_batch_size`, the backward agent's batch; the forward agent's is half of it (IBC's
    ForwardBackwardReplayBufferWrapper). segment_length: None takes the task's (baselines/ibc/tasks.py);
    set, it replaces it (short segments for tests)."""

    sac: SACConfig = dataclasses.field(default_factory=_ibc_sac)
    random_steps: int = 400
    her_relabel: float = 0.8
    pool_size: int = 1000
    slots: int = 50
    match_first: int = 5
    match_every: int = 20
    cost_c: float = 3.0
    cost_l: float = 5.0
    value_samples: int = 10
    goal_draws: int = 2
    segment_length: int | None = None

    def __post_init__(self):
        for name in ("pool_size", "slots", "match_first", "match_every", "cost_l", "value_samples",
                     "goal_draws"):
            if getattr(self, name) <= 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        for name in ("random_steps", "cost_c"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        if self.segment_length is not None and self.segment_length <= 0:
            raise ValueError(f"segment_length must be > 0, got {self.segment_length}")
        if not 0.0 <= self.her_relabel <= 1.0:
            raise ValueError(f"her_relabel must be in [0, 1], got {self.her_relabel}")
        if self.sac.batch_size < 2:  # the forward agent samples half a batch
            raise ValueError(f"sac.batch_size must be >= 2, got {self.sac.batch_size}")


@dataclasses.dataclass(frozen=True)
class ModelFreeConfig:
    """classifier: R3L's goal classifier. discriminator: MEDAL's backward reward, a classifier of
    demonstration states against backward states; its defaults are MEDAL's (medal.yaml;
    docs/baselines.md, "MEDAL"), the same values R3L's classifier takes as its template.
    chunk_len: env steps per compiled call (each step acts, steps the env, stores and updates once).
    replay_capacity: transitions kept per buffer (MEDAL keeps 5e6; our runs are shorter, and 1e6 of
    PointUMaze transitions is ~110 MB per buffer). switch_every: R3L's forward/backward segment length
    (FBRL's policy_switch_frequency). The seed phase (no updates; oracle_sac acts uniformly, r3l with its
    untrained policies) is run.prefill, which these agents set to MEDAL's 10,000."""

    sac: SACConfig = dataclasses.field(default_factory=SACConfig)
    classifier: ClassifierConfig = dataclasses.field(default_factory=ClassifierConfig)
    discriminator: ClassifierConfig = dataclasses.field(default_factory=ClassifierConfig)
    rnd: RNDConfig = dataclasses.field(default_factory=RNDConfig)
    ibc: IBCConfig = dataclasses.field(default_factory=IBCConfig)
    chunk_len: int = 1000
    replay_capacity: int = 1_000_000
    switch_every: int = 300

    def __post_init__(self):
        for name in ("chunk_len", "replay_capacity", "switch_every"):
            if getattr(self, name) <= 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
