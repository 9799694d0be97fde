"""The agent registry: every agent a run accepts (`agent=<name>`), one entry each.

    entry = AGENTS["morefree"]          # run.AgentEntry: name, description, config_sections,
                                        # make_run_fns, prefill, configure
    fns = make_run_fns(config, env)     # the RunFns of config.run.agent (run.py's contract)

The world-model agents are the variants of one learner (variants.py); the model-free baselines are their
own subpackages of baselines/, each exporting its entry as `AGENT`. Adding a baseline adds one line below.
`make train AGENT=x`, the CLIs' "valid agents" line and config.resolve_config read this table only.
"""

from __future__ import annotations

import dataclasses

from morefree_jax import run, variants
from morefree_jax.baselines.ibc import segments as ibc
from morefree_jax.baselines.medal import agent as medal
from morefree_jax.baselines.oracle_sac import agent as oracle_sac
from morefree_jax.baselines.r3l import agent as r3l

WORLD_MODEL_SECTIONS = ("agent", "planner", "schedule")


def _world_model_entry(name: str, chosen: variants.Variant) -> run.AgentEntry:
    return run.AgentEntry(name, chosen.description, WORLD_MODEL_SECTIONS, run.make_run_fns,
                          configure=variants.apply_variant)


AGENTS: dict[str, run.AgentEntry] = {
    **{name: _world_model_entry(name, chosen) for name, chosen in variants.VARIANTS.items()},
    oracle_sac.AGENT.name: oracle_sac.AGENT,
    r3l.AGENT.name: r3l.AGENT,
    medal.AGENT.name: medal.AGENT,
    ibc.AGENT.name: ibc.AGENT,
}


def entry(name: str) -> run.AgentEntry:
    """The named agent's entry; an unknown name is a one-line error listing the valid ones."""
    if name not in AGENTS:
        raise ValueError(f"unknown agent {name!r}; valid agents: {', '.join(AGENTS)}")
    return AGENTS[name]


def configure(config, name: str):
    """The root config (config.Config) with the agent's own settings: its prefill (a model-free agent's
    seed phase) and its configure step (a variant's schedule and imagination goals)."""
    chosen = entry(name)
    if chosen.prefill is not None:
        config = dataclasses.replace(config, run=dataclasses.replace(config.run, prefill=chosen.prefill))
    return chosen.configure(config, name) if chosen.configure else config


def make_run_fns(config, env) -> run.RunFns:
    """The pure run functions of `config.run.agent` for `env` (run.RunFns)."""
    return entry(config.run.agent).make_run_fns(config, env)

