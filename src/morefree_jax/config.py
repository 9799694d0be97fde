"""Frozen configuration dataclasses of the learning core and the presets "paper", "cpu", "debug".

`paper` holds the PEG values for state-based tasks (reference/agent.md sections 1-3, 5.3). `cpu` keeps the
architecture and scales widths, batch, ensemble size and imagination starts so that one train step of all
five learners fits in ~100 ms on a 2-core CPU (numbers in experiments/bench_core.py and the README).
`debug` is tiny, for tests. Presets overlay the defaults with `dataclasses.replace`; the run-level configs
(planner, training loop) live in config_run.py.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field


@dataclass(frozen=True)
class OptimizerConfig:
    """Adam with global-norm clipping and decoupled multiplicative weight decay (DreamerV2 optimiser)."""

    lr: float = 8e-5
    eps: float = 1e-5
    clip: float = 100.0
    weight_decay: float = 1e-6


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
    unroll: int = 1  # lax.scan unroll of observe (performance only; bench_core unrolls to count FLOPs)


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


@dataclass(frozen=True)
class DistanceConfig:
    layers: tuple[int, ...] = (400, 400, 400, 400)
    num_pairs: int = 256
    neg_factor: float = 0.0  # point maze 0.0; walker / ant / 3-stack 0.1
    opt: OptimizerConfig = OptimizerConfig()


@dataclass(frozen=True)
class ExploreConfig:
    members: int = 10
    layers: tuple[int, ...] = (400, 400, 400, 400)
    opt: OptimizerConfig = OptimizerConfig(lr=3e-4)
    ac: ActorCriticConfig = ActorCriticConfig(discount=0.99)


@dataclass(frozen=True)
class ReplayConfig:
    capacity: int = 1_000_000
    batch: int = 45
    length: int = 50
    max_bytes: int = 8 * 2**30  # memory the buffer may take; a larger capacity is a clear error


@dataclass(frozen=True)
class AgentConfig:
    wm: WorldModelConfig = field(default_factory=WorldModelConfig)
    gc: ActorCriticConfig = field(default_factory=ActorCriticConfig)
    distance: DistanceConfig = field(default_factory=DistanceConfig)
    explore: ExploreConfig = field(default_factory=ExploreConfig)
    replay: ReplayConfig = field(default_factory=ReplayConfig)
    alpha: float = 0.2  # imagination goals: alpha/2 eval goals, alpha/2 initial states, 1-alpha replay
    imag_starts: int = 0  # posterior states imagination starts from; 0 = every state of the batch (PEG)


def _paper() -> AgentConfig:
    gc = ActorCriticConfig(unroll=15)
    return AgentConfig(gc=gc, explore=ExploreConfig(ac=gc))


def _cpu() -> AgentConfig:
    # Chosen by measurement (experiments/bench_core.py, README): the paper's structure (layer counts,
    # horizon, heads, losses) with every width 128 (stoch 32), batch 16 x 50, 64 imagination starts
    # (random subset of the 800 posteriors) and 4 ensemble members; imagination scans fully unrolled.
    # The imagination parts scale with the starts: 64 -> ~80 ms per train step, 96 -> ~100, 128 -> ~140
    # on the idle 2-core machine, so 64 keeps the step inside the 100 ms budget with a margin.
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
