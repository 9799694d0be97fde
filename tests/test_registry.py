"""The agent registry (morefree_jax/registry.py) and the layering it keeps: every agent resolves through
its entry, the core names no baseline, and no module imports itself back (imports inside functions
counted)."""

from __future__ import annotations

import ast
import pathlib
import re

import pytest

import envs_mjx
from morefree_jax import registry, variants
from morefree_jax.config import ConfigError, resolve_config
from morefree_jax.run import AgentEntry

REPO = pathlib.Path(__file__).resolve().parents[1]
PACKAGES = {"morefree_jax": REPO / "src" / "morefree_jax", "envs_mjx": REPO / "envs_mjx",
            "experiments": REPO / "experiments"}


def test_every_variant_and_baseline_is_one_entry():
    assert set(variants.VARIANTS) < set(registry.AGENTS)
    for name, entry in registry.AGENTS.items():
        assert isinstance(entry, AgentEntry) and entry.name == name and entry.description
        assert entry.config_sections


@pytest.mark.parametrize("name", list(registry.AGENTS))
def test_each_agent_resolves_with_its_entrys_prefill_and_settings(name):
    config = resolve_config(["env=point_umaze", f"agent={name}"], envs_mjx.ALL_ENVS)
    entry = registry.entry(name)
    default_prefill = resolve_config(["env=point_umaze", "agent=morefree"], envs_mjx.ALL_ENVS).run.prefill
    assert config.run.prefill == (entry.prefill if entry.prefill is not None else default_prefill)
    if name in variants.VARIANTS:
        assert config.schedule.kind == variants.variant(name).schedule_kind
        assert config.agent.alpha == variants.variant(name).imagination_alpha


def test_an_unknown_agent_lists_the_registry():
    with pytest.raises(ConfigError) as error:
        resolve_config(["env=point_umaze", "agent=nope"], envs_mjx.ALL_ENVS)
    assert str(error.value) == f"unknown agent 'nope'; valid agents: {', '.join(registry.AGENTS)}"


def _modules() -> dict[str, pathlib.Path]:
    modules = {}
    for package, root in PACKAGES.items():
        for path in root.rglob("*.py"):
            parts = [package, *path.relative_to(root).with_suffix("").parts]
            modules[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return modules


def _imported(module: str, path: pathlib.Path, known) -> set[str]:
    """Every known module `module` imports, at the top or inside a function."""
    base = module.split(".") if path.name == "__init__.py" else module.split(".")[:-1]
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            source = ".".join(base[:len(base) - node.level + 1] + [node.module or ""]).strip(".") \
                if node.level else node.module
            names = [f"{source}.{alias.name}" for alias in node.names] + [source]
        else:
            continue
        for name in names:
            while name and name not in known:
                name = name.rpartition(".")[0]
            if name and name != module:
                found.add(name)
    return found


def test_no_import_cycle_counting_imports_inside_functions():
    modules = _modules()
    graph = {module: _imported(module, path, modules) for module, path in modules.items()}
    done, on_path = set(), []

    def visit(module):
        if module in on_path:
            cycle = on_path[on_path.index(module):] + [module]
            raise AssertionError("import cycle: " + " -> ".join(cycle))
        if module in done:
            return
        on_path.append(module)
        for imported in sorted(graph[module]):
            visit(imported)
        on_path.pop()
        done.add(module)

    for module in sorted(graph):
        visit(module)


def test_the_core_names_no_baseline():
    baselines = [name for name in registry.AGENTS if name not in variants.VARIANTS]
    quoted = re.compile("|".join(f'"{name}"' for name in baselines))
    allowed = (PACKAGES["morefree_jax"] / "baselines", PACKAGES["morefree_jax"] / "registry.py")
    offenders = [f"{path.relative_to(REPO)}:{number}"
                 for path in _modules().values() if not path.is_relative_to(allowed[0]) and path != allowed[1]
                 for number, line in enumerate(path.read_text().splitlines(), 1) if quoted.search(line)]
    assert offenders == []


def test_train_help_lists_every_agent_of_the_registry(capsys):
    from experiments import train as train_cli

    assert train_cli.main(["--help"]) == 0
    listed = capsys.readouterr().out.split("Agents:\n")[1].splitlines()
    assert [line.split()[0] for line in listed] == list(registry.AGENTS)
