"""The imitation remedies side by side: BC-only success on the validation and test seeds with
95 % Wilson intervals, how the test episodes end, and the copycat probe, read from the files the
runs wrote (docs/recipes.md prints its output).

    python scripts/imitation_table.py --manifest=remedies.json

The manifest lists the rows: ``{"rows": [{"label": "...", "val": ".../metrics.json", "test":
".../metrics.json", "probe": "probe.json", "probe_policy": "<the --policy.path given to the
probe>", "cost": "what the pretraining cost"}]}`` (``val``, ``probe`` and ``cost`` optional).
Metrics files come from ``lerobot-crowdnav-eval --eval.split=val|test``, probe files from
``scripts/probe_sensitivity.py --output=...``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from lerobot_crowdnav.cli import run_cli
from lerobot_crowdnav.measure.metrics import wilson_interval

HEADER = ["remedy", "val SR (%) [95 % CI]", "test SR (%) [95 % CI]", "test human CR (%)", "test wall CR (%)",
          "test TR (%)", "velocity follow", "goal turn (deg)", "pretraining cost"]


@dataclass
class TableConfig:
    # The JSON manifest of the rows (see the module docstring).
    manifest: Path | None = None


def success_cell(path: str | None) -> str:
    """``SR [lo, hi]`` of a metrics file, in %."""
    if not path:
        return "n/a"
    m = json.loads(Path(path).read_text())
    lo, hi = wilson_interval(round(m["sr"] * m["n_episodes"]), m["n_episodes"])
    return f"{100 * m['sr']:.1f} [{100 * lo:.1f}, {100 * hi:.1f}]"


def row(spec: dict) -> list[str]:
    test = json.loads(Path(spec["test"]).read_text())
    probe = ["n/a", "n/a"]
    if spec.get("probe"):
        p = json.loads(Path(spec["probe"]).read_text())["policies"][spec["probe_policy"]]
        probe = [f"{p['velocity_follow']:.2f}", f"{p['goal_turn_deg']:.1f}"]
    return [spec["label"], success_cell(spec.get("val")), success_cell(spec["test"]),
            *(f"{100 * test[k]:.1f}" for k in ("cr_human", "cr_wall", "tr")), *probe, spec.get("cost", "")]


def table(manifest: dict) -> str:
    lines = ["| " + " | ".join(HEADER) + " |", "|" + "---|" * len(HEADER)]
    lines += ["| " + " | ".join(row(spec)) + " |" for spec in manifest["rows"]]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    def run(cfg: TableConfig) -> None:
        if cfg.manifest is None or not Path(cfg.manifest).exists():
            raise FileNotFoundError(f"--manifest={cfg.manifest}: no such file")
        print(table(json.loads(Path(cfg.manifest).read_text())))

    run_cli(TableConfig, run, argv)


if __name__ == "__main__":
    main()
