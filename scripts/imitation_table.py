"""The imitation remedies side by side: BC-only success on the validation and test seeds with
95 % Wilson intervals, how the test episodes end, and the copycat probe, read from the files the
runs wrote (docs/recipes.md prints its output); and, for a BC trained longer, its validation success
against epochs as a table and a figure.

    python scripts/imitation_table.py --manifest=remedies.json [--plot=docs/figures/bc_epochs.png]

The manifest lists the rows: ``{"rows": [{"label": "...", "val": ".../metrics.json", "test":
".../metrics.json", "probe": "probe.json", "probe_policy": "<the --policy.path given to the
probe>", "cost": "what the pretraining cost"}]}`` (``val``, ``probe`` and ``cost`` optional).
Metrics files come from ``lerobot-crowdnav-eval --eval.split=val|test``, probe files from
``scripts/probe_sensitivity.py --output=...``.

An optional ``"curve"`` adds success against epochs: ``{"label": "...", "frames": <dataset frames>,
"batch": <lerobot-train batch>, "points": [{"step": 30000, "val": ".../metrics.json", "probe":
"probe.json", "probe_policy": "..."}, ...], "references": [{"label": "...", "val": ".../metrics.json",
"probe": ..., "probe_policy": ...}]}`` (``probe`` optional); the references (other policies on the
same validation seeds and probe states) are drawn as horizontal lines.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from lerobot_crowdnav.cli import run_cli
from lerobot_crowdnav.measure.metrics import rate_interval

HEADER = ["remedy", "val SR (%) [95 % CI]", "test SR (%) [95 % CI]", "test human CR (%)", "test wall CR (%)",
          "test TR (%)", "velocity follow", "goal turn (deg)", "pretraining cost"]


CURVE_HEADER = ["lerobot-train steps", "epochs", "val SR (%) [95 % CI]", "val human CR (%)", "val wall CR (%)",
                "val TR (%)", "velocity follow", "goal turn (deg)"]


@dataclass
class TableConfig:
    # The JSON manifest of the rows and the optional curve (see the module docstring).
    manifest: Path | None = None
    # Where to draw the manifest's curve (PNG): validation success (with its Wilson interval) and the
    # velocity follow against epochs.
    plot: Path | None = None


def load(path: str) -> dict:
    return json.loads(Path(path).read_text())


def success(m: dict) -> tuple[float, float, float]:
    """Success rate of a metrics file's contents and its 95 % Wilson interval, in %."""
    lo, hi = rate_interval(m["sr"], m["n_episodes"])
    return 100 * m["sr"], 100 * lo, 100 * hi


def success_text(m: dict) -> str:
    """``SR [lo, hi]`` in %."""
    return "{:.1f} [{:.1f}, {:.1f}]".format(*success(m))


def success_cell(path: str | None) -> str:
    """``SR [lo, hi]`` of a metrics file, in %."""
    return success_text(load(path)) if path else "n/a"


def probe(spec: dict) -> dict | None:
    """The probe's figures of the spec's ``probe_policy``, if the spec names a probe file."""
    if not spec.get("probe"):
        return None
    return load(spec["probe"])["policies"][spec["probe_policy"]]


def probe_cells(spec: dict) -> list[str]:
    p = probe(spec)
    return ["n/a", "n/a"] if p is None else [f"{p['velocity_follow']:.2f}", f"{p['goal_turn_deg']:.1f}"]


def row(spec: dict) -> list[str]:
    test = load(spec["test"])
    return [spec["label"], success_cell(spec.get("val")), success_cell(spec["test"]),
            *(f"{100 * test[k]:.1f}" for k in ("cr_human", "cr_wall", "tr")), *probe_cells(spec),
            spec.get("cost", "")]


def markdown(header: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    return "\n".join(lines + ["| " + " | ".join(r) + " |" for r in rows])


def table(manifest: dict) -> str:
    return markdown(HEADER, [row(spec) for spec in manifest["rows"]])


def epochs(curve: dict, step: int) -> float:
    return step * curve["batch"] / curve["frames"]


def curve_table(curve: dict) -> str:
    """Validation success and how the episodes end at each checkpoint of the curve."""
    rows = []
    for point in curve["points"]:
        m = load(point["val"])
        rows.append([f"{point['step']:,}", f"{epochs(curve, point['step']):.1f}", success_text(m),
                     *(f"{100 * m[k]:.1f}" for k in ("cr_human", "cr_wall", "tr")), *probe_cells(point)])
    return markdown(CURVE_HEADER, rows)


def plot_curve(curve: dict, path: Path) -> Path:
    """Validation success (95 % intervals as error bars) and the probe's velocity follow against
    epochs, log scale; the references as horizontal lines (success: with their interval as a band)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    points = sorted(curve["points"], key=lambda p: p["step"])
    x = [epochs(curve, p["step"]) for p in points]
    sr, lo, hi = (list(v) for v in zip(*(success(load(p["val"])) for p in points), strict=True))
    fig, (ax, ax_v) = plt.subplots(1, 2, figsize=(11, 4), dpi=120)
    ax.errorbar(x, sr, yerr=[[s - l for s, l in zip(sr, lo)], [h - s for s, h in zip(sr, hi)]], marker="o",
                capsize=3, color="C0", label=curve["label"])
    probed = [(e, pr["velocity_follow"]) for e, pr in zip(x, map(probe, points)) if pr is not None]
    if probed:
        ax_v.plot(*zip(*probed), marker="o", color="C0", label=curve["label"])
    for i, ref in enumerate(curve.get("references", []), start=1):
        if ref.get("val"):
            r, r_lo, r_hi = success(load(ref["val"]))
            ax.axhspan(r_lo, r_hi, color=f"C{i}", alpha=0.15)
            ax.axhline(r, color=f"C{i}", ls="--", label=ref["label"])
        if (ref_probe := probe(ref)) is not None:
            ax_v.axhline(ref_probe["velocity_follow"], color=f"C{i}", ls="--", label=ref["label"])
    ax.set_ylabel("validation success (%), BC only")
    ax.set_ylim(0, 100)
    ax_v.set_ylabel("velocity follow (1: copies its velocity)")
    ax_v.set_ylim(0, 1.05)
    for a in (ax, ax_v):
        a.set_xscale("log")
        a.set_xticks([t for t in (1, 2, 5, 10, 20, 50, 100, 200) if min(x) / 1.5 <= t <= max(x) * 1.5])
        a.xaxis.set_major_formatter(matplotlib.ticker.FuncFormatter(lambda v, _: f"{v:g}"))
        a.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        a.set_xlabel("epochs over the demonstrations")
        a.grid(alpha=0.3)
        a.legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)
    return path


def main(argv: list[str] | None = None) -> None:
    def run(cfg: TableConfig) -> None:
        if cfg.manifest is None or not Path(cfg.manifest).exists():
            raise FileNotFoundError(f"--manifest={cfg.manifest}: no such file")
        manifest = load(cfg.manifest)
        if cfg.plot is not None and "curve" not in manifest:
            raise ValueError(f"--plot={cfg.plot}: the manifest has no curve to draw")
        blocks = [table(manifest)] if manifest.get("rows") else []
        if "curve" in manifest:
            blocks.append(curve_table(manifest["curve"]))
        print("\n\n".join(blocks))
        if cfg.plot is not None:
            print(f"figure: {plot_curve(manifest['curve'], Path(cfg.plot))}")

    run_cli(TableConfig, run, argv)


if __name__ == "__main__":
    main()
