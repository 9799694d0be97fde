"""Named agents and the root config they resolve to (no compilation)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import envs_mjx
from morefree_jax.config import Config, ConfigError, config_from_dict, config_to_dict, resolve_config
from morefree_jax.imagination import SOURCE_EVAL, GoalPools, sample_imagination_goals
from morefree_jax.variants import VARIANTS, variant

# (schedule kind, collection alpha, imagination alpha, explore policy) per the issue and the paper.
EXPECTED = {
    "morefree": ("back_and_forth", 0.2, 0.2, True),
    "rf_peg": ("planner", 0.0, 0.0, True),
    "peg": ("episodic_planner", 0.0, 0.0, True),
    "dreamer_gc": ("eval_only", 0.0, 2.0, False),
    "mf_no_bfge": ("planner", 0.0, 0.2, True),
    "mf_no_imag": ("back_and_forth", 0.2, 0.0, True),
    "mf_task_only": ("back_and_forth", 1.0, 1.0, True),
}


def resolve(*arguments):
    return resolve_config(list(arguments), envs_mjx.ALL_ENVS)


@pytest.mark.parametrize("name", list(EXPECTED))
def test_variant_sets_collection_and_imagination_goals(name):
    config = resolve("env=point_umaze", f"agent={name}", "preset=debug")
    kind, collect_alpha, imagination_alpha, explore = EXPECTED[name]
    assert (config.schedule.kind, config.schedule.alpha, config.agent.alpha) == (kind, collect_alpha,
                                                                                 imagination_alpha)
    assert variant(name).explore is explore


def test_every_variant_is_covered_and_unknown_names_list_the_valid_ones():
    assert set(VARIANTS) == set(EXPECTED)
    with pytest.raises(ValueError, match="unknown agent 'moorfree'; valid agents: morefree, rf_peg, peg"):
        variant("moorfree")


def test_dreamer_gc_imagines_only_evaluation_goals():
    config = resolve("env=point_umaze", "agent=dreamer_gc", "preset=debug")
    pools = GoalPools(jnp.ones((3, 6)), 2 * jnp.ones((3, 6)))
    _, source = sample_imagination_goals(jax.random.PRNGKey(0), jnp.zeros((500, 6)), pools,
                                         config.agent.alpha, 500)
    assert np.all(np.asarray(source) == SOURCE_EVAL)


def test_layers_preset_task_planner_variant_then_overrides():
    config = resolve("env=point_umaze", "agent=morefree", "preset=cpu", "seed=3", "steps=5e4",
                     "wm.deter=64", "schedule.alpha=0.3", "planner.iterations=7", "eval_every=500")
    assert config.agent.wm.deter == 64 and config.agent.wm.stoch == 32  # cpu preset underneath
    assert config.planner.method == "cem" and config.planner.horizon == 50  # point_umaze planner defaults
    assert config.schedule.alpha == 0.3 and config.agent.alpha == 0.2  # override beats the variant
    assert config.planner.iterations == 7
    assert (config.run.seed, config.run.total_steps, config.run.eval_every) == (3, 50_000, 500)
    assert config_from_dict(Config, config_to_dict(config)) == config


@pytest.mark.parametrize("arguments, message", [
    (["env=maze"], "unknown env 'maze'; valid envs: point_umaze"),
    (["agent=sac"], "unknown agent 'sac'; valid agents: morefree"),
    (["preset=huge"], "unknown preset 'huge'; valid presets: paper, cpu, debug"),
    (["wm.detr=3"], "unknown key 'agent.wm.detr'; valid keys at 'agent.wm': deter"),
    (["colour=red"], "unknown key 'colour'; valid keys: env, agent, preset, seed, steps"),
    (["steps=lots"], "steps expects int, got 'lots'"),
    (["steps=0"], "steps must be > 0, got 0"),
    (["seed=1.5"], "seed expects int"),
    (["planner.init_std=nan"], "finite"),
    (["agent=rf_peg", "alpha=0.1"], "sets the paper's alpha of morefree, mf_task_only, not of agent rf_peg"),
    (["agent=oracle_sac", "alpha=0.1"], "not of agent oracle_sac"),
    (["alpha=0.5", "schedule.alpha=0.2"], "give it or them, not schedule.alpha=0.2 too"),
])
def test_bad_input_is_a_one_line_error_naming_what_is_valid(arguments, message):
    given = {argument.split("=")[0] for argument in arguments}  # a key given twice is its own error
    base = [arg for arg in ("env=point_umaze", "agent=morefree") if arg.split("=")[0] not in given]
    with pytest.raises(ConfigError) as error:
        resolve(*base, *arguments)
    assert message in str(error.value) and "\n" not in str(error.value)


@pytest.mark.parametrize("agent", ["morefree", "mf_task_only"])
def test_alpha_sets_the_papers_alpha_in_collection_and_imagination(agent):
    config = resolve("env=point_umaze", f"agent={agent}", "alpha=0.7")
    assert (config.schedule.kind, config.schedule.alpha, config.agent.alpha) == ("back_and_forth", 0.7, 0.7)
    separate = resolve("env=point_umaze", f"agent={agent}", "schedule.alpha=0.7", "agent.alpha=0.7")
    assert separate == config


@pytest.mark.parametrize("task, expected", [
    # PEG ant maze (docs/tasks.md, "Per-task defaults"): entropy 1e-5, discount and P2E discount 0.996,
    # negatives 0.1.
    ("ant", dict(entropy=1e-5, discount=0.996, p2e_discount=0.996, neg_factor=0.1, subgoal=2.0,
                 steps=800_000, train_every=2, prefill=2_500)),
    # The Fetch family takes PEG's 3-block stacking: entropy 1e-5, negatives 0.1, discounts 0.99.
    ("push_hard", dict(entropy=1e-5, discount=0.99, p2e_discount=0.99, neg_factor=0.1, subgoal=1.0,
                       steps=500_000, train_every=2, prefill=3_750)),
    # PEG point maze: entropy 1e-4, no negatives.
    ("point_umaze", dict(entropy=1e-4, discount=0.99, p2e_discount=0.99, neg_factor=0.0, subgoal=1.0,
                         steps=200_000, train_every=2, prefill=2_500)),
    ("tabletop", dict(entropy=1e-4, discount=0.99, p2e_discount=0.99, neg_factor=0.0, subgoal=2.0,
                      steps=200_000, train_every=1, prefill=2_500)),
    ("sawyer_door", dict(entropy=1e-5, discount=0.99, p2e_discount=0.99, neg_factor=0.1, subgoal=2.0,
                         steps=400_000, train_every=5, prefill=2_500)),
])
@pytest.mark.parametrize("preset_name", ["paper", "cpu"])
def test_resolved_config_carries_the_task_values(task, expected, preset_name):
    config = resolve(f"env={task}", "agent=morefree", f"preset={preset_name}")
    agent, run = config.agent, config.run
    assert agent.gc.entropy == agent.explore.ac.entropy == expected["entropy"]
    assert (agent.gc.discount, agent.explore.ac.discount) == (expected["discount"], expected["p2e_discount"])
    assert agent.distance.neg_factor == expected["neg_factor"]
    assert (run.subgoal_threshold, run.total_steps) == (expected["subgoal"], expected["steps"])
    assert (run.train_every, run.prefill) == (expected["train_every"], expected["prefill"])
    written = config_to_dict(config)  # what config.json records
    assert written["agent"]["gc"]["entropy"] == expected["entropy"]
    assert written["run"]["total_steps"] == expected["steps"]
    # Any key still overrides the task's value.
    changed = resolve(f"env={task}", "agent=morefree", "gc.entropy=3e-3", "steps=9000", "train_every=7")
    assert (changed.agent.gc.entropy, changed.run.total_steps, changed.run.train_every) == (3e-3, 9000, 7)


def test_every_task_declares_its_defaults_in_one_place():
    import envs_mjx

    for task in envs_mjx.ALL_ENVS:
        defaults = envs_mjx.env_class(task).default_config()
        assert {"run.total_steps", "run.train_every", "agent.gc.entropy", "planner.method"} <= set(defaults)
