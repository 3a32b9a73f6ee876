"""Figures (matplotlib, Agg backend): written as PNG files, nothing shown on screen."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402


def _smooth(y: np.ndarray, window: int) -> np.ndarray:
    """Trailing moving average that ignores NaN (iterations where no episode ended)."""
    out = np.full(len(y), np.nan)
    for i in range(len(y)):
        part = y[max(0, i - window + 1): i + 1]
        if np.isfinite(part).any():
            out[i] = np.nanmean(part)
    return out


def plot_finetune_curves(runs: dict[str, list[dict]], path: str | Path, smooth: int = 5) -> Path:
    """Training success rate and average episode reward against environment steps (the paper's
    fine-tuning figure), one line per run; validation success rates as markers.

    ``runs`` maps a label to the records of a run's ``progress.jsonl`` (keys ``env_steps``,
    ``train/success_rate``, ``train/episode_return`` and, where validated, ``val/success_rate``).
    """
    fig, (ax_sr, ax_ret) = plt.subplots(1, 2, figsize=(11, 4), dpi=120)
    for i, (label, records) in enumerate(runs.items()):
        color = f"C{i}"
        steps = np.array([r["env_steps"] for r in records], dtype=float)
        sr = np.array([np.nan if r.get("train/success_rate") is None else r["train/success_rate"] for r in records])
        ret = np.array([np.nan if r.get("train/episode_return") is None else r["train/episode_return"] for r in records])
        ax_sr.plot(steps, 100 * _smooth(sr, smooth), color=color, label=f"{label} (train)")
        ax_ret.plot(steps, _smooth(ret, smooth), color=color, label=label)
        val = [(r["env_steps"], r["val/success_rate"]) for r in records if r.get("val/success_rate") is not None]
        if val:
            vs, vsr = zip(*val, strict=True)
            ax_sr.plot(vs, 100 * np.array(vsr), "o--", color=color, markersize=4, alpha=0.8, label=f"{label} (validation)")
    ax_sr.set(xlabel="environment steps", ylabel="success rate (%)", title="Success rate", ylim=(0, 100))
    ax_ret.set(xlabel="environment steps", ylabel="average episode reward", title="Average episode reward")
    for ax in (ax_sr, ax_ret):
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
        ax.ticklabel_format(axis="x", style="sci", scilimits=(0, 3))
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)
    return path
