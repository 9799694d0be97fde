"""Frozen configuration dataclasses of the learning core and the presets "paper", "cpu", "debug".

`paper` holds the PEG values for state-based tasks (docs/learner.md, "Presets"; the values in its sections
"World model (RSSM)", "Goal-conditioned actor-critic", "Temporal distance", "Plan2Explore" and "Replay").
`cpu` keeps the architecture and scales widths, batch, ensemble size and imagination starts so that one train
step of all five learners fits in ~100 ms on a 2-core CPU (numbers in experiments/benchmarks/core.py and
docs/performance.md, "Learning core"). `debug` is tiny, for tests. Presets overlay the defaults with
`dataclasses.replace`; the run-level configs (planner, training loop) live in config.py.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

from morefree_jax.precision import CHOICES as PRECISION_CHOICES
from morefree_jax.precision import check_precision


def _positive(config, *names: str) -> None:
    """ValueError unless each field (a number, or every width of a non-empty tuple) is > 0."""
    for name in names:
        value = getattr(config, name)
        values = value if isinstance(value, tuple) else (value,)
        if not values or any(v <= 0 for v in values):
            raise ValueError(f"{name} must be > 0{' (every entry)' if isinstance(value, tuple) else ''}, "
                             f"got {value}")


def _within(config, name: str, low: float, high: float) -> None:
    value = getattr(config, name)
    if not low <= value <= high:
        raise ValueError(f"{name} must be in [{low}, {high}], got {value}")



@dataclass(frozen=True)
class OptimizerConfig:
    """Adam with global-norm clipping and decoupled multiplicative weight decay (DreamerV2 optimiser)."""

    lr: float = 8e-5
    eps: float = 1e-5
    clip: float = 100.0
    weight_decay: float = 1e-6

    def __post_init__(self):
        _positive(self, "lr", "eps", "clip")
        _within(self, "weight_decay", 0.0, 1.0)


@dataclass(frozen=True)
class WorldModelConfig:
    deter: int = 200
    hidden: int = 200
    stoch: int = 50
    min_std: float = 0.1
    encoder_layers: tuple[int, ...] = (400, 400, 400)  # embed size = last width
    decoder_layers: tuple[int, ...] = (400, 400, 400)
    embed_head_layers: tuple[int, ...] = (400, 400, 400)
    kl_balance: float = 0.8
    kl_free: float = 1.0
    kl_scale: float = 1.0
    opt: OptimizerConfig = OptimizerConfig(lr=3e-4)
    unroll: int = 1  # lax.scan unroll of observe: performance only (the core benchmark unrolls it)
    gru_bias: bool = True  # DreamerV2's GRU input layer has a bias; run dirs made before this key had none

    def __post_init__(self):
        _positive(self, "deter", "hidden", "stoch", "min_std", "encoder_layers", "decoder_layers",
                  "embed_head_layers", "unroll")
        _within(self, "kl_balance", 0.0, 1.0)
        if self.kl_free < 0 or self.kl_scale < 0:
            raise ValueError(f"kl_free and kl_scale must be >= 0, got {self.kl_free}, {self.kl_scale}")


@dataclass(frozen=True)
class ActorCriticConfig:
    actor_layers: tuple[int, ...] = (400, 400, 400, 400)
    critic_layers: tuple[int, ...] = (400, 400, 400, 400)
    actor_min_std: float = 0.1
    horizon: int = 15
    discount: float = 0.99
    lambda_: float = 0.95
    entropy: float = 1e-4
    target_every: int = 100  # hard copy of the critic into the target critic, first update copies
    # lax.scan unroll of imagination (performance only). Unrolling the short horizon lets XLA schedule the
    # backward pass as straight-line code: measured faster on CPU, at the price of compile time.
    unroll: int = 1
    actor_opt: OptimizerConfig = OptimizerConfig()
    critic_opt: OptimizerConfig = OptimizerConfig()

    def __post_init__(self):
        _positive(self, "actor_layers", "critic_layers", "actor_min_std", "horizon", "discount",
                  "target_every", "unroll")
        _within(self, "discount", 0.0, 1.0)
        _within(self, "lambda_", 0.0, 1.0)
        if self.entropy < 0:
            raise ValueError(f"entropy must be >= 0, got {self.entropy}")


@dataclass(frozen=True)
class DistanceConfig:
    layers: tuple[int, ...] = (400, 400, 400, 400)
    num_pairs: int = 256
    neg_factor: float = 0.0  # point maze 0.0; walker / ant / 3-stack 0.1
    opt: OptimizerConfig = OptimizerConfig()

    def __post_init__(self):
        _positive(self, "layers", "num_pairs")
        _within(self, "neg_factor", 0.0, 1.0)


@dataclass(frozen=True)
class ExploreConfig:
    members: int = 10
    layers: tuple[int, ...] = (400, 400, 400, 400)
    opt: OptimizerConfig = OptimizerConfig(lr=3e-4)
    ac: ActorCriticConfig = ActorCriticConfig(discount=0.99)

    def __post_init__(self):
        _positive(self, "layers")
        if self.members < 2:  # the exploration reward is the members' disagreement
            raise ValueError(f"members must be >= 2, got {self.members}")


@dataclass(frozen=True)
class ReplayConfig:
    capacity: int = 1_000_000
    batch: int = 45
    length: int = 50
    max_bytes: int = 8 * 2**30  # memory the buffer may take; a larger capacity is a clear error

    def __post_init__(self):
        _positive(self, "capacity", "batch", "max_bytes")
        if self.length < 2:
            raise ValueError(f"length must be >= 2 (a sequence), got {self.length}")


@dataclass(frozen=True)
class AgentConfig:
    wm: WorldModelConfig = field(default_factory=WorldModelConfig)
    gc: ActorCriticConfig = field(default_factory=ActorCriticConfig)
    distance: DistanceConfig = field(default_factory=DistanceConfig)
    explore: ExploreConfig = field(default_factory=ExploreConfig)
    replay: ReplayConfig = field(default_factory=ReplayConfig)
    alpha: float = 0.2  # imagination goals: alpha/2 eval goals, alpha/2 initial states, 1-alpha replay
    imag_starts: int = 0  # posterior states imagination starts from; 0 = every state of the batch (PEG)
    # Min-max normalise observations by the task's observation_bounds (envs_mjx/normalise.py), as PEG does
    # for block stacking; the Fetch tasks, which take that config, turn it on.
    normalise_observations: bool = False
    # Matmul inputs in bfloat16 with float32 accumulation ("bf16") or float32 throughout ("f32"); "auto": the
    # faster on the machine the run starts on (precision.py), the concrete choice recorded in the run dir and
    # kept on resume. Default f32: bf16 runs are faster but have not yet been shown to learn as well
    # (docs/learner.md, "Precision").
    precision: str = "f32"

    def __post_init__(self):
        check_precision(self.precision, PRECISION_CHOICES)
        _within(self, "alpha", 0.0, 2.0)  # 2: every imagination goal an evaluation goal (dreamer_gc)
        if self.imag_starts < 0:
            raise ValueError(f"imag_starts must be >= 0 (0: every posterior state), got {self.imag_starts}")


def _paper() -> AgentConfig:
    gc = ActorCriticConfig(unroll=15)
    return AgentConfig(gc=gc, explore=ExploreConfig(ac=gc))


def _cpu() -> AgentConfig:
    # Chosen by measurement (experiments/benchmarks/core.py; docs/performance.md, "Learning core"): the
    # paper's structure (layer counts, horizon, heads, losses) with every width 128 (stoch 32), batch 16 x 50,
    # 64 imagination starts (random subset of the 800 posteriors) and 4 ensemble members; imagination scans
    # fully unrolled. The imagination parts scale with the starts; 64 keeps the step inside the 100 ms
    # budget with a margin (the timings per start count are in docs/performance.md).
    width = (128, 128, 128)
    wm = WorldModelConfig(deter=128, hidden=128, stoch=32, encoder_layers=width, decoder_layers=width,
                          embed_head_layers=width)
    mlp = (128, 128, 128, 128)
    gc = ActorCriticConfig(actor_layers=mlp, critic_layers=mlp, unroll=15)
    explore = ExploreConfig(members=4, layers=mlp, ac=gc)
    return AgentConfig(
        wm=wm, gc=gc, distance=DistanceConfig(layers=mlp), explore=explore,
        replay=ReplayConfig(batch=16, length=50), imag_starts=64,
    )


def _debug() -> AgentConfig:
    small = (32, 32)
    wm = WorldModelConfig(
        deter=32, hidden=32, stoch=8, encoder_layers=small, decoder_layers=small, embed_head_layers=small,
        opt=OptimizerConfig(lr=1e-3),
    )
    gc = ActorCriticConfig(actor_layers=small, critic_layers=small, horizon=5, target_every=5)
    explore = ExploreConfig(members=3, layers=small, ac=gc)
    return AgentConfig(
        wm=wm, gc=gc, distance=DistanceConfig(layers=small, num_pairs=64, neg_factor=0.1), explore=explore,
        replay=ReplayConfig(capacity=10_000, batch=4, length=10), imag_starts=0,
    )


PRESETS = {"paper": _paper, "cpu": _cpu, "debug": _debug}


def preset(name: str) -> AgentConfig:
    """The named preset; unknown names are an error listing the valid ones."""
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; valid presets: {', '.join(PRESETS)}")
    return PRESETS[name]()


def replace(config, **changes):
    """`dataclasses.replace` re-exported so callers overlay presets without importing dataclasses."""
    return dataclasses.replace(config, **changes)
