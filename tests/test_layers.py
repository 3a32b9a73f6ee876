"""Imports only go down: every import (module- or function-level, absolute or relative) of every
module of ``lerobot_crowdnav`` and of the plugins targets a module of the same or a lower layer
(docs/architecture.md). A new module must be given a layer here."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = {  # top-level package -> its directory
    "lerobot_crowdnav": ROOT / "lerobot_crowdnav",
    "lerobot_env_crowdnav": ROOT / "plugins" / "lerobot_env_crowdnav" / "lerobot_env_crowdnav",
    "lerobot_policy_pdpo": ROOT / "policies" / "lerobot_policy_pdpo" / "lerobot_policy_pdpo",
    "lerobot_policy_crowdnavpp": ROOT / "policies" / "lerobot_policy_crowdnavpp" / "lerobot_policy_crowdnavpp",
}
EV = "lerobot_crowdnav.evaluation"
# Lowest first. A module belongs to the layer of its longest listed prefix (a package or a module).
LAYERS: list[tuple[str, list[str]]] = [
    ("base", ["lerobot_crowdnav.layout", "lerobot_crowdnav.cli", "lerobot_crowdnav.fault",
              "lerobot_crowdnav.checkpoint_files"]),
    # The package's __init__ registers the gymnasium envs (reads sim.config), hence this layer.
    ("sim", ["lerobot_crowdnav", "lerobot_crowdnav.sim", "lerobot_env_crowdnav"]),
    ("evaluation core", [EV, f"{EV}.metrics", f"{EV}.episodes", f"{EV}.plots", f"{EV}.parameters"]),
    ("data", ["lerobot_crowdnav.data"]),
    ("policy", ["lerobot_policy_pdpo", "lerobot_policy_crowdnavpp"]),
    ("rl", ["lerobot_crowdnav.rl"]),
    ("evaluation CLIs and report", [f"{EV}.eval", f"{EV}.baselines", f"{EV}.figures", f"{EV}.report"]),
    ("main job", ["lerobot_crowdnav.pipeline", "lerobot_crowdnav.fault_injection"]),
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
    ("lerobot_crowdnav.sim.engine", "from ..evaluation.metrics import EpisodeRecord"),  # sim -> evaluation
    ("lerobot_crowdnav.data.collect", "import lerobot_crowdnav.rl.loop"),  # absolute, data -> rl
    ("lerobot_crowdnav.evaluation.report", "def write_report():\n    from ..pipeline import SHORT\n"),  # the old cycle
    ("lerobot_crowdnav.rl.validation", "from ..evaluation.eval import main"),  # rl -> evaluation CLI
    ("lerobot_crowdnav.layout", "from . import fault, sim"),  # base -> sim (a package named in an import list)
    ("lerobot_crowdnav.sim.envs", "from ..nowhere import x"),  # a module with no layer
])
def test_the_check_fails_on_an_upward_import(module, source):
    assert violations(module, source, False, set(all_modules())), source


def test_same_and_lower_layers_pass():
    known = set(all_modules())
    assert violations("lerobot_crowdnav.rl.validation", "from ..evaluation.episodes import run_episodes\n"
                      "from .loop import restart_memory\nimport numpy", False, known) == []
