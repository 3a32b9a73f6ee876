"""Figures (matplotlib, Agg backend): written as PNG files, nothing shown on screen."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.lines import Line2D  # noqa: E402
from matplotlib.patches import Circle  # noqa: E402

from ..sim.envs import structured  # noqa: E402


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
    fine-tuning figure), and success rate against training wall time, one line per run;
    validation success rates as markers; a fourth panel with the validation intrusion rate when
    some run logged it (runs from before validation ran the intrusion test did not).

    ``runs`` maps a label to the records of a run's ``progress.jsonl`` (keys ``env_steps``,
    ``train/success_rate``, ``train/episode_return``, ``time/wall_s`` and, where validated,
    ``val/success_rate`` and ``val/intrusion_rate``).
    """
    with_itr = any(r.get("val/intrusion_rate") is not None for records in runs.values() for r in records)
    fig, axes = plt.subplots(1, 3 + with_itr, figsize=(16 + 5 * with_itr, 4), dpi=120)
    ax_sr, ax_ret, ax_time = axes[:3]
    for i, (label, records) in enumerate(runs.items()):
        color = f"C{i}"
        column = lambda key: np.array([np.nan if r.get(key) is None else r[key] for r in records], dtype=float)  # noqa: E731
        steps, sr, hours = column("env_steps"), column("train/success_rate"), column("time/wall_s") / 3600
        hours[0] = 0.0 if np.isnan(hours[0]) else hours[0]  # the pretrained policy's validation
        ax_sr.plot(steps, 100 * _smooth(sr, smooth), color=color, label=f"{label} (train)")
        ax_ret.plot(steps, _smooth(column("train/episode_return"), smooth), color=color, label=label)
        ax_time.plot(hours, 100 * _smooth(sr, smooth), color=color, label=f"{label} (train)")
        val = np.array([(s, h, r["val/success_rate"]) for s, h, r in zip(steps, hours, records, strict=True)
                        if r.get("val/success_rate") is not None]).reshape(-1, 3)
        if len(val):
            ax_sr.plot(val[:, 0], 100 * val[:, 2], "o--", color=color, markersize=4, alpha=0.8, label=f"{label} (validation)")
            ax_time.plot(val[:, 1], 100 * val[:, 2], "o--", color=color, markersize=4, alpha=0.8,
                         label=f"{label} (validation)")
        itr = column("val/intrusion_rate")
        if not np.isnan(itr).all():
            logged = ~np.isnan(itr)
            axes[3].plot(steps[logged], 100 * itr[logged], "o--", color=color, markersize=4, label=f"{label} (validation)")
    ax_sr.set(xlabel="environment steps", ylabel="success rate (%)", title="Success rate", ylim=(0, 100))
    ax_ret.set(xlabel="environment steps", ylabel="average episode reward", title="Average episode reward")
    ax_time.set(xlabel="training wall time (h)", ylabel="success rate (%)", title="Success rate against wall time",
                ylim=(0, 100))
    if with_itr:
        axes[3].set(xlabel="environment steps", ylabel="ITR (%)", title="Validation intrusion rate", ylim=(0, None))
    for ax in axes:
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    for ax in (ax_sr, ax_ret, *axes[3:]):
        ax.ticklabel_format(axis="x", style="sci", scilimits=(0, 3))
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)
    return path


# -- action-chunk figures (robot-centred scenes) -------------------------------------------------
FIG_DPI = 150
PANEL_INCHES = (3.2, 3.4)  # width, height of one scene panel (axes, title and tick labels)
LEGEND_INCHES = 0.6  # band under the panels for the shared legend
MAX_COLUMNS = 5
DRAWN_HUMAN_RADIUS = 0.3  # m; the observation has no human radius (paper preset: 0.3 to 0.5)
ROBOT_COLOR = "#1e9e3c"
HUMAN_COLOR = "#285ad8"
GOAL_COLOR = "#f0a000"
CHUNK_COLOR = "#7b2cbf"
CROSS_COLOR = "#dc1e1e"
SENSING_COLOR = "#808080"
WALL_COLOR = "#3c3c3c"


def chunk_positions(chunks: np.ndarray, dt: float) -> np.ndarray:
    """Planned robot positions ``(..., H + 1, 2)`` relative to the current one: the origin, then
    the running sum of each chunk's velocities ``(..., H, 2)`` (m/s) times ``dt``."""
    chunks = np.asarray(chunks, dtype=float)
    steps = np.cumsum(chunks * dt, axis=-2)
    return np.concatenate([np.zeros_like(steps[..., :1, :]), steps], axis=-2)


def _scene_figure(n: int, title: str | None):
    """A figure of ``n`` panels (a row, or rows of MAX_COLUMNS), legend band at the bottom."""
    ncols = min(n, MAX_COLUMNS)
    nrows = -(-n // MAX_COLUMNS)
    size = (PANEL_INCHES[0] * ncols, PANEL_INCHES[1] * nrows + LEGEND_INCHES + (0.3 if title else 0.0))
    fig = plt.figure(figsize=size, dpi=FIG_DPI, layout="constrained")
    axes = fig.subplots(nrows, ncols, squeeze=False)
    for ax in axes.flat[n:]:
        ax.axis("off")
    if title:
        fig.suptitle(title)
    return fig, axes.flat[:n]


def _draw_scene(ax, obs: np.ndarray, sensing_range: float, half_width: float,
                arena_size: float | None = None) -> None:
    """One robot-centred scene: walls (if ``arena_size``), the sensing circle (sensing range
    plus the robot's radius: visibility is on surface distance), the robot at the origin,
    the visible humans with their predicted positions, and the goal (clipped to the panel edge
    with an arrow when outside). Axes in metres, world orientation."""
    s = structured(np.asarray(obs, dtype=float))
    robot_pos, robot_radius, goal = s.robot[0:2], float(s.robot[2]), s.robot[3:5]
    lim = half_width
    ax.set(xlim=(-lim, lim), ylim=(-lim, lim), aspect="equal", xlabel="x (m)", ylabel="y (m)")
    ax.tick_params(labelsize=7)
    ax.xaxis.label.set_size(8)
    ax.yaxis.label.set_size(8)
    if arena_size is not None:  # the workspace walls, relative to the robot
        a = arena_size
        corners = np.array([[-a, -a], [a, -a], [a, a], [-a, a], [-a, -a]]) - robot_pos
        ax.plot(corners[:, 0], corners[:, 1], color=WALL_COLOR, lw=2, zorder=1)
    # A human is visible when its surface is within sensing_range of the robot's surface.
    ax.add_patch(Circle((0, 0), sensing_range + robot_radius, fill=False, ls="--", lw=0.8, ec=SENSING_COLOR, zorder=1))

    fade = np.linspace(1.0, 0.25, s.humans.shape[-2])
    marker_colors = [(*matplotlib.colors.to_rgb(HUMAN_COLOR), a) for a in fade]
    for rows in s.humans[s.mask > 0.5]:  # (L+1, 2) positions k = 0..L relative to the robot
        ax.add_patch(Circle(rows[0], DRAWN_HUMAN_RADIUS, fc=HUMAN_COLOR, ec=HUMAN_COLOR, alpha=0.85, lw=0.5, zorder=3))
        ax.plot(rows[:, 0], rows[:, 1], color=HUMAN_COLOR, lw=0.8, alpha=0.7, zorder=3)
        ax.scatter(rows[1:, 0], rows[1:, 1], s=5, c=marker_colors[1:], lw=0, zorder=3)

    ax.add_patch(Circle((0, 0), robot_radius, fc=ROBOT_COLOR, ec="black", lw=0.5, zorder=4))

    rel = goal - robot_pos
    if np.max(np.abs(rel)) <= lim - 0.4:
        ax.plot(*rel, marker="*", ms=13, color=GOAL_COLOR, mec="black", mew=0.5, ls="none", zorder=6)
    else:  # off the panel: a star inside the edge, an arrow from it toward the goal, the distance
        unit = rel / np.linalg.norm(rel)
        tip = rel * (lim - 0.15) / np.max(np.abs(rel))
        star = tip - 0.16 * lim * unit
        ax.annotate("", xy=tip, xytext=star, zorder=6,
                    arrowprops=dict(arrowstyle="-|>", color=GOAL_COLOR, lw=1.8, shrinkA=4, shrinkB=0))
        ax.plot(*star, marker="*", ms=10, color=GOAL_COLOR, mec="black", mew=0.5, ls="none", zorder=6)
        # The distance beside the arrow (planned paths tend to run along it), on the side further
        # from the panel edge, the text running toward the panel's middle.
        side = np.array([-unit[1], unit[0]]) * 0.12 * lim
        at = min((star + side, star - side), key=lambda q: (round(np.max(np.abs(q)), 6), -q[1]))
        ax.text(*at, f"goal {np.linalg.norm(rel):.1f} m", ha="left" if at[0] < 0 else "right", va="center",
                fontsize=7, zorder=6, bbox=dict(boxstyle="round,pad=0.15", fc="white", ec="none", alpha=0.8))


def _draw_chunks(ax, chunks: np.ndarray, dt: float, alpha: float, lw: float) -> None:
    """Planned paths of chunks ``(N, H, 2)`` (m/s) from the origin, each ending in a red cross."""
    paths = chunk_positions(chunks, dt)
    for p in paths:
        ax.plot(p[:, 0], p[:, 1], color=CHUNK_COLOR, lw=lw, alpha=alpha, zorder=5, solid_capstyle="round")
    ax.scatter(paths[:, -1, 0], paths[:, -1, 1], marker="x", s=14 if len(paths) == 1 else 8,
               c=CROSS_COLOR, lw=1.2 if len(paths) == 1 else 0.8, alpha=min(1.0, 3 * alpha), zorder=7)


def _scene_legend(fig, chunk_label: str, walls: bool, sensing: bool = True) -> None:
    handles = [
        Line2D([], [], marker="o", ms=8, color=ROBOT_COLOR, mec="black", mew=0.5, ls="none", label="robot"),
        Line2D([], [], color=SENSING_COLOR, ls="--", lw=0.8, label="sensing range"),
        Line2D([], [], marker="o", ms=7, color=HUMAN_COLOR, lw=0.8, label="human + predicted path (0.25 s steps)"),
        Line2D([], [], marker="*", ms=11, color=GOAL_COLOR, mec="black", mew=0.5, ls="none", label="goal"),
        Line2D([], [], color=CHUNK_COLOR, lw=1.5, label=chunk_label),
        Line2D([], [], marker="x", ms=6, color=CROSS_COLOR, mew=1.2, ls="none", label="chunk end"),
    ]
    if not sensing:  # the circle lies outside zoomed panels
        handles = [h for h in handles if h.get_label() != "sensing range"]
    if walls:
        handles.append(Line2D([], [], color=WALL_COLOR, lw=2, label="wall"))
    fig.legend(handles=handles, loc="outside lower center", ncols=min(len(handles), 4), fontsize=8, frameon=False)


def _save(fig, path: str | Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)
    return path


def plot_storyboard(snapshots: list[dict], path: str | Path, sensing_range: float, dt: float,
                    title: str | None = None, arena_size: float | None = None) -> Path:
    """Robot-centred snapshots of one episode, one panel each (rows of 5): the scene and the
    sampled action chunk as the path the robot plans (velocities integrated over ``dt``).

    ``snapshots``: dicts ``{"obs": (269,), "chunk": (H, 2) m/s, "t": s}``. ``arena_size``: draw
    the walls of the bounded workspace ``[-arena_size, arena_size]^2``. Panels span
    ``+-(sensing_range + 1)`` m. Figure: ``PANEL_INCHES`` per panel plus a legend band, ``FIG_DPI``.
    """
    if not snapshots:
        raise ValueError("no snapshots to draw")
    fig, axes = _scene_figure(len(snapshots), title)
    for ax, snap in zip(axes, snapshots, strict=True):
        _draw_scene(ax, snap["obs"], sensing_range, sensing_range + 1.0, arena_size)
        _draw_chunks(ax, np.asarray(snap["chunk"])[None], dt, alpha=1.0, lw=2.0)
        ax.set_title(f"t = {snap['t']:.2f} s", fontsize=9)
    horizon = len(snapshots[0]["chunk"])
    _scene_legend(fig, f"action chunk: planned path ({horizon * dt:.2f} s)", arena_size is not None)
    return _save(fig, path)


def plot_multimodality(snapshots: list[dict], path: str | Path, sensing_range: float, dt: float,
                       title: str | None = None, arena_size: float | None = None,
                       half_width: float = 3.0) -> Path:
    """Many chunks sampled for the same observation, drawn together semi-transparently, for
    several steps side by side (the diffusion policy's multimodality).

    ``snapshots``: dicts ``{"obs": (269,), "chunks": (N, H, 2) m/s, "t": s}``. Panels span
    ``+-half_width`` m (default 3: a zoom on the chunks, at most ``v_pref * H * dt`` long);
    ``arena_size`` as in :func:`plot_storyboard`. Figure size as :func:`plot_storyboard`'s.
    """
    if not snapshots:
        raise ValueError("no snapshots to draw")
    fig, axes = _scene_figure(len(snapshots), title)
    for ax, snap in zip(axes, snapshots, strict=True):
        chunks = np.asarray(snap["chunks"])
        _draw_scene(ax, snap["obs"], sensing_range, half_width, arena_size)
        _draw_chunks(ax, chunks, dt, alpha=0.3, lw=1.0)
        ax.set_title(f"t = {snap['t']:.2f} s ({len(chunks)} samples)", fontsize=9)
    n = len(snapshots[0]["chunks"])
    _scene_legend(fig, f"{n} sampled action chunks (planned paths)", arena_size is not None,
                  sensing=half_width > sensing_range)
    return _save(fig, path)
