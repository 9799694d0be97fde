"""Named agents: MoReFree, its MBRL baselines and ablations, as settings of one root config.

Every variant is the same learner; they differ only in where goals come from:
  collection (goal_schedule.ScheduleConfig: kind, alpha) and imagination (AgentConfig.alpha: alpha/2 of the
  goal-conditioned policy's imagination goals are evaluation goals, alpha/2 initial states, the rest replay
  states), plus whether an exploration policy runs after the go phase.

    morefree      Back-and-Forth Go-Explore (alpha 0.2) + the imagination mix (alpha 0.2)      [paper]
    rf_peg        reset-free PEG: a fresh planner goal every chunk, replay goals in imagination [paper 5]
    peg           episodic PEG: one planner goal per hard-reset segment, go until the early switch
                  (at the latest the segment's midpoint), then explore for the rest            [paper 5]
    dreamer_gc    goal-conditioned Dreamer: evaluation goals for the whole stream, no explore policy,
                  imagination goals are evaluation goals only
    mf_no_bfge    ablation: imagination mix only (collection as rf_peg)                         [paper 6]
    mf_no_imag    ablation: Back-and-Forth Go-Explore only (imagination as rf_peg)              [paper 6]
    mf_task_only  ablation: alpha 1 (only task goals in collection and imagination)             [paper 6]

The model-free baselines are agents of the same runs with other learners (baselines/, each its own
subpackage); registry.py lists every agent, these and those.

dreamer_gc sets AgentConfig.alpha = 2: the imagination mix draws an evaluation goal with probability
alpha/2, so 2 makes every imagination goal an evaluation goal without a separate switch in the core.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple


class Variant(NamedTuple):
    schedule_kind: str  # goal_schedule.SCHEDULE_KINDS
    collect_alpha: float  # ScheduleConfig.alpha (back_and_forth only)
    imagination_alpha: float  # AgentConfig.alpha
    explore: bool  # an exploration phase follows the go phase
    description: str


VARIANTS: dict[str, Variant] = {
    "morefree": Variant("back_and_forth", 0.2, 0.2, True, "MoReFree: back-and-forth go-explore + goal mix"),
    "rf_peg": Variant("planner", 0.0, 0.0, True, "reset-free PEG: planner goal every chunk"),
    "peg": Variant("episodic_planner", 0.0, 0.0, True, "episodic PEG: one planner goal per reset segment"),
    "dreamer_gc": Variant("eval_only", 0.0, 2.0, False, "goal-conditioned Dreamer on evaluation goals"),
    "mf_no_bfge": Variant("planner", 0.0, 0.2, True, "MoReFree without back-and-forth go-explore"),
    "mf_no_imag": Variant("back_and_forth", 0.2, 0.0, True, "MoReFree without the imagination goal mix"),
    "mf_task_only": Variant("back_and_forth", 1.0, 1.0, True, "MoReFree with alpha 1 (task goals only)"),
}


def variant(name: str) -> Variant:
    """The named variant; unknown names are an error listing the valid ones."""
    if name not in VARIANTS:
        raise ValueError(f"unknown agent {name!r}; valid agents: {', '.join(VARIANTS)}")
    return VARIANTS[name]


def paper_alpha_agents() -> list[str]:
    """The variants whose collection and imagination use one alpha, the paper's: `alpha=` sets both."""
    return [name for name, chosen in VARIANTS.items()
            if chosen.schedule_kind == "back_and_forth" and chosen.collect_alpha == chosen.imagination_alpha]


def apply_variant(config, name: str):
    """The root config (config.Config) with the variant's schedule and imagination settings.
    Planner goals are searched afresh for every planner chunk; episodic PEG makes its one goal choice per
    hard-reset segment, so it searches once per segment (paper appendix, baselines)."""
    chosen = variant(name)
    schedule = dataclasses.replace(config.schedule, kind=chosen.schedule_kind, alpha=chosen.collect_alpha)
    agent = dataclasses.replace(config.agent, alpha=chosen.imagination_alpha)
    return dataclasses.replace(config, schedule=schedule, agent=agent)
