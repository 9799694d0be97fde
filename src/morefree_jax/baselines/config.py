"""Settings of the model-free baselines (`Config.baseline`, CLI keys `baseline.*`), with their sources.

The SAC learner's values are MEDAL's (reference/baselines.md section 2). R3L's classifier and RND values
are the templates baselines.md section 5 names (MEDAL's discriminator, DI-engine's RND), since MoReFree does
not state its own; where we had to choose, the field's comment says what and why. Importing it starts no
JAX backend (config_run imports it before the CLIs configure the runtime).
"""

from __future__ import annotations

import dataclasses


@dataclasses.dataclass(frozen=True)
class SACConfig:
    """baselines.md section 2 (MEDAL `cfgs/oracle.yaml`, `agents.py`). target_entropy None: -|A|/2."""

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

    def __post_init__(self):
        for name in ("feature_dim", "hidden_dim", "lr", "init_temperature", "batch_size"):
            if getattr(self, name) <= 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        for name in ("discount", "tau"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"{name} must be in [0, 1], got {getattr(self, name)}")


MODEL_FREE_AGENTS = {
    "oracle_sac": "Oracle: episodic SAC on the evaluation task, sparse reward (the only agent with resets)",
    "r3l": "R3L: forward SAC on a learned goal classifier, backward RND exploration (no env reward)",
    "medal": "MEDAL: forward SAC on the sparse reward, backward SAC back to demonstration states (demos)",
}


@dataclasses.dataclass(frozen=True)
class ClassifierConfig:
    """R3L's VICE-style goal classifier, on MEDAL's discriminator template (baselines.md sections 3, 5):
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
    (baselines.md section 5): target and predictor MLPs [64, 64, 128], predictor Adam 1e-3, batch 64,
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


@dataclasses.dataclass(frozen=True)
class ModelFreeConfig:
    """classifier: R3L's goal classifier. discriminator: MEDAL's backward reward, a classifier of
    demonstration states against backward states; its defaults are MEDAL's (medal.yaml, baselines.md
    section 3), the same values R3L's classifier takes as its template.
    chunk_len: env steps per compiled call (each step acts, steps the env, stores and updates once).
    replay_capacity: transitions kept per buffer (MEDAL keeps 5e6; our runs are shorter, and 1e6 of
    PointUMaze transitions is ~110 MB per buffer). switch_every: R3L's forward/backward segment length
    (FBRL's policy_switch_frequency). The seed phase (uniform random actions, no updates) is run.prefill,
    which these agents set to MEDAL's 10,000."""

    sac: SACConfig = dataclasses.field(default_factory=SACConfig)
    classifier: ClassifierConfig = dataclasses.field(default_factory=ClassifierConfig)
    discriminator: ClassifierConfig = dataclasses.field(default_factory=ClassifierConfig)
    rnd: RNDConfig = dataclasses.field(default_factory=RNDConfig)
    chunk_len: int = 1000
    replay_capacity: int = 1_000_000
    switch_every: int = 300

    def __post_init__(self):
        for name in ("chunk_len", "replay_capacity", "switch_every"):
            if getattr(self, name) <= 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
