"""Every entry point answers a malformed value with one ``error: ...`` line and no traceback (draccus'
decoder used to end in two chained tracebacks), and its ``--help`` explains every option. The cases cover every console script, every module
run with ``python -m`` and every script of scripts/ and datasets_scripts/;
``test_every_entry_point_has_a_case`` fails when a new one has none. Parsing fails before any
work starts, so each case only imports its command."""

from __future__ import annotations

import importlib
import re
import runpy
import sys
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).parents[1]

# Entry point -> a malformed value of one of its typed settings and the field draccus names.
DRACCUS = {
    "lerobot_crowdnav.evaluation.eval": ("--eval.n_episodes=abc", "eval.n_episodes"),
    "lerobot_crowdnav.sim.benchmark": ("--repeats=abc", "repeats"),
    "lerobot_crowdnav.rl.finetune": ("--env_steps=abc", "env_steps"),
    "lerobot_crowdnav.rl.train_ppo": ("--env_steps=abc", "env_steps"),
    "lerobot_crowdnav.pipeline": ("--demos=x", "demos"),
    "lerobot_crowdnav.evaluation.baselines": ("--n_episodes=abc", "n_episodes"),
    "lerobot_crowdnav.evaluation.figures": ("--n_samples=abc", "n_samples"),
    "lerobot_crowdnav.evaluation.tables": ("--check=maybe", "check"),
    "lerobot_crowdnav.data.collect": ("--episodes=1x", "episodes"),
    "lerobot_crowdnav.data.dagger": ("--round=abc", "round"),
    "lerobot_crowdnav.data.hub": ("--overwrite=maybe", "overwrite"),
    "scripts/crowdnavpp_curve.py": ("--window=abc", "window"),
    "scripts/crowdnavpp_reward_terms.py": ("--episodes=abc", "episodes"),
    "scripts/probe_exploration.py": ("--episodes=abc", "episodes"),
    "scripts/probe_sensitivity.py": ("--every=x", "every"),
    "datasets_scripts/collect_orca.py": ("--episodes=1x", "episodes"),
    "datasets_scripts/push_dataset.py": ("--overwrite=maybe", "overwrite"),
}
# The benchmark scripts parse with argparse: its usage line and one "error: argument" line.
ARGPARSE = {
    "scripts/bench_bc.py": ["--repeats=abc"],
    "scripts/bench_finetune.py": ["--policy.path=x", "--setting=a", "--num_envs=abc"],
    "scripts/bench_loader.py": ["--repeats=abc"],
    "scripts/bench_sampling.py": ["--policy.path=x", "--episodes=abc"],
}
# Its only setting is a path (any text is one): a missing file is its bad value.
OTHER = {"scripts/imitation_table.py": ("--manifest=nowhere.json", "--manifest=nowhere.json: no such file")}


def entry_points() -> set[str]:
    """The console scripts' modules, the package's modules with a ``__main__`` block, the scripts."""
    scripts = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]
    found = {target.split(":")[0] for target in scripts.values()}
    for path in (ROOT / "lerobot_crowdnav").rglob("*.py"):
        if 'if __name__ == "__main__":' in path.read_text():
            found.add(".".join(path.relative_to(ROOT).with_suffix("").parts))
    found |= {str(p.relative_to(ROOT)) for d in ("scripts", "datasets_scripts") for p in (ROOT / d).glob("*.py")}
    return found


def run(entry: str, argv: list[str], monkeypatch) -> None:
    """``entry`` as its command runs it: ``main()`` on the process's arguments."""
    if entry.endswith(".py"):
        monkeypatch.setattr(sys, "argv", [entry, *argv])
        monkeypatch.syspath_prepend(str((ROOT / entry).parent))
        runpy.run_path(str(ROOT / entry), run_name="__main__")
    else:
        monkeypatch.setattr(sys, "argv", [entry, *argv])
        importlib.import_module(entry).main()


def test_every_entry_point_has_a_case():
    assert entry_points() == set(DRACCUS) | set(ARGPARSE) | set(OTHER)


@pytest.mark.parametrize("entry", sorted(DRACCUS))
def test_a_malformed_value_is_one_error_line(entry, monkeypatch, capsys):
    arg, name = DRACCUS[entry]
    with pytest.raises(SystemExit) as exc:
        run(entry, [arg], monkeypatch)
    message = exc.value.code
    assert isinstance(message, str), f"expected a message, got exit code {message!r}"
    assert message.startswith(f"error: `{name}`: Couldn't parse") and "\n" not in message, message
    assert exc.value.__suppress_context__  # raised "from None": Python prints the line alone
    assert "Traceback" not in capsys.readouterr().err


@pytest.mark.parametrize("entry", sorted(ARGPARSE))
def test_a_malformed_value_in_a_benchmark_script_is_argparse_usage_and_error(entry, monkeypatch, capsys):
    with pytest.raises(SystemExit) as exc:
        run(entry, ARGPARSE[entry], monkeypatch)
    lines = capsys.readouterr().err.strip().splitlines()
    assert exc.value.code == 2 and lines[0].startswith("usage: ") and "Traceback" not in "\n".join(lines)
    assert lines[-1] == f"{Path(entry).name}: error: argument {ARGPARSE[entry][-1].split('=')[0]}: invalid int value: 'abc'"


@pytest.mark.parametrize(("settings", "says"), [("128:4", "each setting has 3 or 4 fields"), ("128:x:0", "integers")])
def test_a_malformed_bench_bc_setting_is_an_argparse_error(settings, says, monkeypatch, capsys):
    with pytest.raises(SystemExit) as exc:
        run("scripts/bench_bc.py", [f"--settings={settings}"], monkeypatch)
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert exc.value.code == 2 and last.startswith(f"bench_bc.py: error: --settings={settings}: ") and says in last


@pytest.mark.parametrize("entry", sorted(OTHER))
def test_a_bad_value_of_a_path_setting_is_one_error_line(entry, monkeypatch, capsys, tmp_path):
    monkeypatch.chdir(tmp_path)
    arg, expected = OTHER[entry]
    with pytest.raises(SystemExit) as exc:
        run(entry, [arg], monkeypatch)
    assert exc.value.code == f"error: {expected}"
    assert "Traceback" not in capsys.readouterr().err


def undocumented_options(help_text: str) -> list[str]:
    """The options of an argparse/draccus ``--help`` text that have no help text: nothing after the
    option on its line and no indented continuation on the next (draccus takes a field's help from
    the comment right above it, so a field under another field's comment has none)."""
    lines = help_text.splitlines()
    bad = []
    for line, after in zip(lines, [*lines[1:], ""]):
        m = re.match(r"^  (--[\w.\-]+)(?: \S+)?(?:\s{2,}(?P<help>.*))?$", line)
        if m and m.group(1) not in ("--help", "--config_path") and not (m.group("help") or "").strip() \
                and not re.match(r"^ {20,}\S", after):
            bad.append(m.group(1))
    return bad


def test_undocumented_options_are_found():
    text = "options:\n  --a int               Its help.\n  --b_long_name list[int]\n                        Wrapped help.\n" \
           "  --c str               \n  --d float\n\nGroup:\n"
    assert undocumented_options(text) == ["--c", "--d"]


@pytest.mark.parametrize("entry", sorted(DRACCUS) + sorted(ARGPARSE) + sorted(OTHER))
def test_help_explains_every_option(entry, monkeypatch, capsys):
    with pytest.raises(SystemExit) as exc:
        run(entry, ["--help"], monkeypatch)
    assert exc.value.code in (0, None)
    text = capsys.readouterr().out
    assert "--" in text and undocumented_options(text) == []
