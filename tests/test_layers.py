"""Imports only go down: every import (module- or function-level, absolute or relative) of every
module of ``lerobot_crowdnav`` and of the plugins targets a module of the same or a lower layer
(docs/architecture.md). A new module must be given a layer here. And the package ships only what
the product uses: every module is reached by imports from an entry point (a console script, a
module run with ``python -m``, the plugins lerobot discovers, the scripts); code only the tests
use lives in tests/ (e.g. tests/fault_injection.py)."""

from __future__ import annotations

import ast
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = {  # top-level package -> its directory
    "lerobot_crowdnav": ROOT / "lerobot_crowdnav",
    "lerobot_env_crowdnav": ROOT / "plugins" / "lerobot_env_crowdnav" / "lerobot_env_crowdnav",
    "lerobot_policy_pdpo": ROOT / "policies" / "lerobot_policy_pdpo" / "lerobot_policy_pdpo",
    "lerobot_policy_crowdnavpp": ROOT / "policies" / "lerobot_policy_crowdnavpp" / "lerobot_policy_crowdnavpp",
}
MAIN = "lerobot_crowdnav.main"
# Lowest first. A module belongs to the layer of its longest listed prefix (a package or a module).
LAYERS: list[tuple[str, list[str]]] = [
    ("base", ["lerobot_crowdnav.layout", "lerobot_crowdnav.cli", "lerobot_crowdnav.fault",
              "lerobot_crowdnav.checkpoint_files"]),
    # The package's __init__ registers the gymnasium envs (reads sim.config), hence this layer.
    ("sim", ["lerobot_crowdnav", "lerobot_crowdnav.sim", "lerobot_env_crowdnav"]),
    ("measure: episodes, metrics, plots, parameter counts", ["lerobot_crowdnav.measure"]),
    ("data", ["lerobot_crowdnav.data"]),
    ("policy", ["lerobot_policy_pdpo", "lerobot_policy_crowdnavpp"]),
    ("rl", ["lerobot_crowdnav.rl"]),
    ("evaluation: CLIs, report, tables", ["lerobot_crowdnav.evaluation"]),
    # The main job in parts (lerobot_crowdnav/main/), each above the ones it needs.
    ("main job: config, run folder, row type", [MAIN, f"{MAIN}.config", f"{MAIN}.paths", f"{MAIN}.rows"]),
    ("main job: stage runner", [f"{MAIN}.stages"]),
    ("main job: training stages, evaluation and report", [f"{MAIN}.training", f"{MAIN}.evaluation"]),
    ("main job: sources of rows", [f"{MAIN}.sources"]),
    ("main job: driver (lerobot-crowdnav-main)", ["lerobot_crowdnav.pipeline"]),
]


def layer_of(module: str) -> int | None:
    """Index in LAYERS of ``module`` (longest prefix wins); None if it is not one of ours."""
    best, best_len = None, -1
    for i, (_, prefixes) in enumerate(LAYERS):
        for p in prefixes:
            if (module == p or module.startswith(p + ".")) and len(p) > best_len:
                best, best_len = i, len(p)
    return best


def module_name(package: str, path: Path) -> str:
    parts = [package, *path.relative_to(PACKAGES[package]).with_suffix("").parts]
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def all_modules() -> dict[str, Path]:
    return {module_name(pkg, p): p for pkg, root in PACKAGES.items() for p in sorted(root.rglob("*.py"))}


def imported_modules(module: str, source: str, is_package: bool, known: set[str]) -> list[tuple[int, str]]:
    """(line, target module) for every import statement anywhere in ``source`` (also inside
    functions: the function-level import that hid the pipeline <-> report cycle counts too)."""
    package = module if is_package else module.rpartition(".")[0]
    out = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            out += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[:len(base) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module
            for alias in node.names:  # "from . import fault" imports the module lerobot_crowdnav.fault
                sub = f"{target}.{alias.name}"
                out.append((node.lineno, sub if sub in known else target))
    return out


def violations(module: str, source: str, is_package: bool, known: set[str]) -> list[str]:
    own = layer_of(module)
    bad = []
    for line, target in imported_modules(module, source, is_package, known):
        if target.split(".")[0] not in PACKAGES:
            continue  # third-party or standard library
        layer = layer_of(target) if target in known else None
        if layer is None or layer > own:
            where = "not a module with a layer" if layer is None else f"layer '{LAYERS[layer][0]}'"
            bad.append(f"{module}:{line} ({LAYERS[own][0]}) imports {target} ({where})")
    return bad


def test_every_module_has_a_layer():
    assert [m for m in all_modules() if layer_of(m) is None] == []


def test_imports_only_go_down():
    modules = all_modules()
    known = set(modules)
    bad = [v for m, p in modules.items() for v in violations(m, p.read_text(), p.name == "__init__.py", known)]
    assert bad == [], "\n".join(bad)


@pytest.mark.parametrize("module, source", [
    ("lerobot_crowdnav.sim.engine", "from ..measure.metrics import EpisodeRecord"),  # sim -> measure
    ("lerobot_crowdnav.data.collect", "import lerobot_crowdnav.rl.loop"),  # absolute, data -> rl
    ("lerobot_crowdnav.evaluation.report", "def write_report():\n    from ..pipeline import SHORT\n"),  # the old cycle
    ("lerobot_crowdnav.rl.validation", "from ..evaluation.eval import main"),  # rl -> evaluation CLI
    ("lerobot_crowdnav.layout", "from . import fault, sim"),  # base -> sim (a package named in an import list)
    ("lerobot_crowdnav.sim.envs", "from ..nowhere import x"),  # a module with no layer
    ("lerobot_crowdnav.main.stages", "from .training import Training"),  # within the main job: runner -> training
    ("lerobot_crowdnav.main.evaluation", "from .sources import ShippedModels"),  # evaluation -> a source
    ("lerobot_crowdnav.main.sources", "from ..pipeline import Pipeline"),  # a source -> the driver
])
def test_the_check_fails_on_an_upward_import(module, source):
    assert violations(module, source, False, set(all_modules())), source


def entry_points() -> set[str]:
    """What the product starts from: the console scripts, the modules with a ``__main__`` block
    (``python -m``), the packages lerobot discovers, the modules the scripts import, and the policy
    families' modules (``rl/families.get`` imports ``rl/<type>.py`` by its name)."""
    from lerobot_crowdnav.rl import families

    scripts = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]
    roots = {target.split(":")[0] for target in scripts.values()} | set(PACKAGES)
    roots |= {m for m, p in all_modules().items() if 'if __name__ == "__main__":' in p.read_text()}
    roots |= {f"{families.PACKAGE}.{name}" for name in families.known()}
    known = set(all_modules())
    for script in [*(ROOT / "scripts").glob("*.py"), *(ROOT / "datasets_scripts").glob("*.py")]:
        roots |= {target for _, target in imported_modules("__script__", script.read_text(), False, known)}
    return roots


def reached(roots: set[str], modules: dict[str, Path]) -> set[str]:
    """Every module of ours that importing ``roots`` loads (a module loads its parent packages)."""
    known, seen, todo = set(modules), set(), list(roots)
    while todo:
        module = todo.pop()
        if module in seen or module not in known:
            continue
        seen.add(module)
        todo += [module.rpartition(".")[0]] if "." in module else []
        path = modules[module]
        todo += [t for _, t in imported_modules(module, path.read_text(), path.name == "__init__.py", known)]
    return seen


def test_the_package_ships_only_what_the_product_uses():
    modules = all_modules()
    assert sorted(set(modules) - reached(entry_points(), modules)) == []


def test_the_reach_check_fails_on_a_module_only_tests_import():
    """The fault-injection harness, when it lived in the package with no entry point of its own."""
    modules = {**all_modules(), "lerobot_crowdnav.harness": ROOT / "tests" / "fault_injection.py"}
    assert "lerobot_crowdnav.harness" not in reached(entry_points(), modules)


def test_same_and_lower_layers_pass():
    known = set(all_modules())
    assert violations("lerobot_crowdnav.rl.validation", "from ..measure.episodes import run_episodes\n"
                      "from .loop import restart_memory\nimport numpy", False, known) == []
    assert violations("lerobot_crowdnav.main.sources", "from .training import Training\nfrom .evaluation import Curve\n"
                      "from ..evaluation.report import Budget", False, known) == []
