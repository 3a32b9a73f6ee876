"""The CrowdNav++ baseline's learning curve so far, drawn against the reference's own reward curve
at the same env steps (docs/crowdnavpp.md prints its output).

    python scripts/crowdnavpp_curve.py --run=outputs/bounded_crowdnavpp/crowdnavpp/bounded_s425

reads the run's ``progress.jsonl`` (one line per PPO iteration, written by
``lerobot-crowdnav-train-ppo``; the run may still be going: the file is only read) and the
reference's reward and entropy curves ``docs/data/crowdnavpp_reference_curves.csv``, and writes

* a PNG (``--output_png``): the mean training episode reward per window of ``--window`` env steps
  for the run (with and, where logged, without its prediction penalty) and for the reference's
  two logged trainings; below it the run's validation
  success (every validation, with its 95 % Wilson interval when known, as in the table) and
  training success (per window); at the bottom how its training episodes failed (per window:
  human collision, wall collision, timeout), which tells a dip's cause; and the policy's standard
  deviation against the reference's (PPO's own dynamics: no entropy bonus, so only the updates
  move it);
* with ``--compare`` (other runs' folders: other seeds or starts of the same recipe), their
  training reward without the prediction penalty and training success per window in the same
  figure, which shows the spread between runs;
* a markdown table to stdout (and to ``--output_md`` if given), one row per window the run has
  reached: env steps, the run's training reward, the same without its prediction-penalty part
  (what the reference's log reports, where the run logs that part), the reference's reward
  (rand / non-rand), the
  run's training success and failures (human / wall / timeout), the policy's standard deviation
  (the run's, the reference's rand / non-rand), the latest validation success in the window (with
  its 95 % Wilson interval over the run's ``val.n_episodes``, read from its last checkpoint's
  ``train_ppo_config.json``), and the run's cumulative training wall time (``time/wall_s``) at the
  window's last iteration.

Windows are ``[k W, (k + 1) W)`` for W = ``--window`` env steps, an iteration or a log line
belonging to the window of the env-step count it reports (the count at its end); the run's last
iteration, which ends at or past its budget (``env_steps`` of the same settings), counts in the
budget's last window. The run's training reward and outcome rates of a window are episode-weighted:
the sum over its iterations of ``train/episode_return x train/episodes`` (resp.
``train/<outcome>_rate x train/episodes``) over the sum of ``train/episodes``, i.e. the mean over
every training episode that ended in the window (an outcome a log does not report reads n/a); the
reward without the prediction penalty likewise from ``train/episode_return -
train/prediction_penalty``, over the iterations that log the penalty (a window only part of which
logs it says which share of its episodes it covers, and is drawn hollow). The reference's
``eprewmean`` leaves its predictor's penalty out: its training script averages the returns of its
per-env episode monitors, and the penalty is added to the rewards outside them (by the vectorized
wrapper that runs its GST predictor). The reference's values are plain means over the log lines in
the window: of ``eprewmean`` (its mean return of its last 100 training episodes) and of
``loss/policy_entropy`` (the Gaussian's entropy per action dimension). The policy's standard
deviation is the geometric mean over the two action dimensions, ``exp(H - ln(2 pi e) / 2)`` for an
entropy H per dimension: the run's from the plain mean of its ``entropy`` (summed over the two
dimensions) over the window's iterations. A window the run has not finished is marked "(so far)" in
the table and drawn hollow.

The reference CSV (columns ``env_steps`` = window centre, ``eprewmean_rand``,
``eprewmean_non_rand``, ``entropy_rand``, ``entropy_non_rand``) is this reduction of
``trained_models/GST_predictor_rand/progress.csv`` and
``trained_models/GST_predictor_non_rand/progress.csv`` of Shuijing725/CrowdNav_Prediction_AttnGraph
(columns ``misc/nupdates``, ``misc/total_timesteps``, ``eprewmean``, ``loss/policy_entropy``, ...): given
``--reference_rand_log`` and ``--reference_non_rand_log`` (those two files), the script writes it
to ``--reference`` first (windows the logs cover completely; an empty cell where one log has
ended). Without ``--run`` it stops there.
"""

from __future__ import annotations

import csv
import itertools
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

from lerobot_crowdnav.checkpoint_files import PRETRAINED_MODEL, TRAIN_PPO_CONFIG
from lerobot_crowdnav.cli import run_cli
from lerobot_crowdnav.measure.metrics import rate_interval
from lerobot_crowdnav.rl.run_log import read_progress

ROOT = Path(__file__).resolve().parents[1]
REFERENCE_CSV = ROOT / "docs" / "data" / "crowdnavpp_reference_curves.csv"
DEFAULT_PNG = ROOT / "docs" / "figures" / "crowdnavpp_bounded_curve.png"
# What is reduced from the reference's logs: CSV name -> log column; each gets <name>_rand, <name>_non_rand.
REFERENCE_LOG_COLUMNS = {"eprewmean": "eprewmean", "entropy": "loss/policy_entropy"}
REFERENCE_COLUMNS = tuple(f"{name}_{log}" for name in REFERENCE_LOG_COLUMNS for log in ("rand", "non_rand"))
REWARD_COLUMNS, ENTROPY_COLUMNS = REFERENCE_COLUMNS[:2], REFERENCE_COLUMNS[2:]
ACTION_DIMS = 2  # (vx, vy): the run logs its Gaussian's entropy summed over them
# How a training episode ends: progress.jsonl's train/<outcome>_rate.
OUTCOMES = ("success", "human_collision", "wall_collision", "timeout")
FAILURES = OUTCOMES[1:]
COMPARE_COLOURS = ("tab:olive", "tab:pink", "tab:brown", "tab:gray")  # --compare's runs, in turn
HEADER = ["env steps (window)", "train reward", "train reward without prediction penalty",
          "reference reward, rand", "reference reward, non-rand",
          "train success (%)", "train human / wall collision / timeout (%)",
          "policy std (m/s), this run / reference rand / non-rand",
          "validation success (%) [95 % CI] at env steps", "wall time (h, cumulative)"]


@dataclass
class CurveConfig:
    # The run's folder, holding progress.jsonl (only read). Without it, only the reference CSV is
    # (re)built, from --reference_rand_log and --reference_non_rand_log.
    run: Path | None = None
    # The reference's curves: CSV with env_steps (window centre), eprewmean_rand, eprewmean_non_rand,
    # entropy_rand, entropy_non_rand. Read for the figure and the table; written when the two logs
    # are given.
    reference: Path = REFERENCE_CSV
    # The figure to write (PNG); null to write none.
    output_png: Path | None = DEFAULT_PNG
    # Also write the markdown table to this file (it is always printed).
    output_md: Path | None = None
    # Window width in env steps; the reference CSV must have been reduced with the same width.
    window: int = 250_000
    # Right end of the figure's env-step axis; 0: the run's last env step rounded up to a whole
    # million (at least 1 M).
    x_max: int = 0
    # Figure title; empty: one naming the run's folder, its env steps and its wall time.
    title: str = ""
    # Other runs' folders (a progress.jsonl each: other seeds or starts of the same recipe) drawn
    # beside this one, labelled by folder name: their training reward without the prediction
    # penalty and their training success per finished window, which shows the runs' spread. The
    # table stays this run's.
    compare: list[Path] = field(default_factory=list)
    # The reference's own log trained_models/GST_predictor_rand/progress.csv (randomized humans),
    # to rebuild --reference from.
    reference_rand_log: Path | None = None
    # The reference's own log trained_models/GST_predictor_non_rand/progress.csv (no randomized
    # humans), to rebuild --reference from.
    reference_non_rand_log: Path | None = None


@dataclass
class Window:
    """What a run did in the window ``[k W, (k + 1) W)``."""

    k: int
    first_step: int  # env steps of the window's first and last iteration
    last_step: int
    episodes: int = 0  # training episodes that ended in the window
    reward: float = math.nan  # episode-weighted training return
    # The same without its prediction-penalty part, over the iterations that log that part: what the
    # reference's log reports (its predictor's penalty is added outside its episode monitor).
    reward_without_penalty: float = math.nan
    split_share: float = 0.0  # the share of the window's episodes in the iterations that log the penalty
    rates: dict[str, float] = field(default_factory=dict)  # episode-weighted rate of each of OUTCOMES
    entropy: float = math.nan  # mean policy entropy (summed over the action dimensions) over the iterations
    val_success: float = math.nan  # latest validation success in the window
    val_step: int | None = None
    wall_s: float = math.nan  # cumulative training wall time at the window's last timed iteration
    complete: bool = True

    @property
    def std(self) -> float:
        """The policy's standard deviation in the window (geometric mean over the action dimensions)."""
        return policy_std(self.entropy / ACTION_DIMS)


# -- the reference ------------------------------------------------------------------------------

def reference_log_windows(path: Path, window: int) -> dict[str, dict[int, float]]:
    """``{name: {window index: mean}}`` of each of ``REFERENCE_LOG_COLUMNS`` in one of the
    reference's progress.csv files, for the windows the log covers completely (its last line within
    one logging interval of the window's end)."""
    with open(path, newline="") as f:
        rows = sorted((int(float(r["misc/total_timesteps"])), [float(r[c]) for c in REFERENCE_LOG_COLUMNS.values()])
                      for r in csv.DictReader(f))
    if len(rows) < 2:
        raise ValueError(f"{path}: fewer than two log lines")
    interval = min(b[0] - a[0] for a, b in zip(rows, rows[1:], strict=False))
    by_k: dict[int, list[list[float]]] = {}
    for step, values in rows:
        by_k.setdefault(step // window, []).append(values)
    covered = {k: v for k, v in by_k.items() if rows[-1][0] + interval >= (k + 1) * window}
    return {name: {k: math.fsum(line[i] for line in v) / len(v) for k, v in sorted(covered.items())}
            for i, name in enumerate(REFERENCE_LOG_COLUMNS)}


def write_reference(rand_log: Path, non_rand_log: Path, out: Path, window: int) -> list[dict[str, str]]:
    """Reduce the reference's two logs to ``out`` (env_steps = window centre); returns its rows."""
    logs = [reference_log_windows(rand_log, window), reference_log_windows(non_rand_log, window)]
    curves = [log[name] for name in REFERENCE_LOG_COLUMNS for log in logs]  # in REFERENCE_COLUMNS' order
    rows = [{"env_steps": str(k * window + window // 2),
             **{c: (f"{curve[k]:.6f}" if k in curve else "") for c, curve in zip(REFERENCE_COLUMNS, curves, strict=True)}}
            for k in sorted(set().union(*curves))]
    out.parent.mkdir(parents=True, exist_ok=True)
    with open(out, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=["env_steps", *REFERENCE_COLUMNS], lineterminator="\n")
        w.writeheader()
        w.writerows(rows)
    return rows


def read_reference(path: Path, window: int) -> dict[str, dict[int, float]]:
    """``{column: {window index: value}}`` from the reference CSV (a column it lacks stays empty);
    checks the window width."""
    curves: dict[str, dict[int, float]] = {c: {} for c in REFERENCE_COLUMNS}
    with open(path, newline="") as f:
        for r in csv.DictReader(f):
            centre = int(r["env_steps"])
            if (centre - window // 2) % window:
                raise ValueError(f"{path}: env_steps {centre} is not the centre of a {window}-step window "
                                 "(rebuild it with the same --window)")
            for c in REFERENCE_COLUMNS:
                if r.get(c, ""):
                    curves[c][centre // window] = float(r[c])
    return curves


# -- the run ------------------------------------------------------------------------------------

def run_windows(rows: list[dict], window: int, budget: int | None = None) -> list[Window]:
    """Per-window training reward and outcome rates (episode-weighted), latest validation success
    and cumulative wall time of a run's progress lines. With the run's ``budget`` (env steps), the
    iteration that ends at or past it counts in the budget's last window: mostly run before the
    budget, it would otherwise make a window of its own, a point drawn from a handful of episodes."""
    by_k: dict[int, list[dict]] = {}
    for r in rows:
        step = int(r["env_steps"])
        by_k.setdefault((budget - 1) // window if budget and step >= budget else step // window, []).append(r)
    steps = sorted({int(r["env_steps"]) for r in rows})
    interval = min((b - a for a, b in zip(steps, steps[1:], strict=False) if b > a), default=window)
    out = []
    for k in sorted(by_k):
        rs = sorted(by_k[k], key=lambda r: int(r["env_steps"]))
        w = Window(k, int(rs[0]["env_steps"]), int(rs[-1]["env_steps"]))
        train = [r for r in rs if r.get("train/episodes") and r.get("train/episode_return") is not None]
        w.episodes = sum(int(r["train/episodes"]) for r in train)
        if w.episodes:
            w.reward = math.fsum(r["train/episode_return"] * r["train/episodes"] for r in train) / w.episodes
            split = [r for r in train if r.get("train/prediction_penalty") is not None]
            if split:
                n_split = sum(int(r["train/episodes"]) for r in split)
                w.reward_without_penalty = math.fsum(
                    (r["train/episode_return"] - r["train/prediction_penalty"]) * r["train/episodes"] for r in split
                ) / n_split
                w.split_share = n_split / w.episodes
            for o in OUTCOMES:
                w.rates[o] = (math.fsum(r[f"train/{o}_rate"] * r["train/episodes"] for r in train) / w.episodes
                              if all(r.get(f"train/{o}_rate") is not None for r in train) else math.nan)
        entropies = [r["entropy"] for r in rs if r.get("entropy") is not None]
        if entropies:
            w.entropy = math.fsum(entropies) / len(entropies)
        val = [r for r in rs if r.get("val/success_rate") is not None]
        if val:
            w.val_success, w.val_step = float(val[-1]["val/success_rate"]), int(val[-1]["env_steps"])
        timed = [r["time/wall_s"] for r in rs if r.get("time/wall_s") is not None]
        if timed:
            w.wall_s = float(max(timed))
        w.complete = w.last_step + interval >= (k + 1) * window
        out.append(w)
    return out


# -- outputs ------------------------------------------------------------------------------------

def _num(x: float, fmt: str) -> str:
    return "n/a" if x is None or math.isnan(x) else format(x, fmt)


def policy_std(entropy_per_dim: float) -> float:
    """A Gaussian's standard deviation from its entropy per dimension (geometric mean over dimensions)."""
    return math.exp(entropy_per_dim - 0.5 * math.log(2 * math.pi * math.e))


def _rate(w: Window, outcome: str) -> str:
    return _num(100 * w.rates.get(outcome, math.nan), ".1f")


def _interval(rate: float, n: int | None) -> str:
    if not n:
        return ""
    lo, hi = rate_interval(rate, n)
    return f" [{100 * lo:.0f}, {100 * hi:.0f}]"


def run_settings(run: Path) -> dict:
    """The run's settings, from its last checkpoint (empty without one): its validation episodes
    per reading and its budget."""
    settings = run / "checkpoints" / "last" / PRETRAINED_MODEL / TRAIN_PPO_CONFIG
    return json.loads(settings.read_text()) if settings.exists() else {}


def table(windows: list[Window], reference: dict[str, dict[int, float]], window: int,
          val_episodes: int | None = None) -> str:
    """The markdown table; each validation success with its Wilson interval when the number of
    validation episodes is known."""
    lines = ["| " + " | ".join(HEADER) + " |", "|" + "---|" * len(HEADER)]
    for w in windows:
        end = (w.k + 1) * window if w.complete else w.last_step
        span = f"{w.k * window:,}-{end:,}" + ("" if w.complete else " (so far)")
        val = "" if w.val_step is None else f"{100 * w.val_success:.0f}{_interval(w.val_success, val_episodes)} at {w.val_step:,}"
        stds = [w.std, *(policy_std(reference[c].get(w.k, math.nan)) for c in ENTROPY_COLUMNS)]
        without = _num(w.reward_without_penalty, ".2f") + (f" ({100 * w.split_share:.0f} % of its episodes)"
                                                             if 0 < w.split_share < 1 else "")
        cells = [span, _num(w.reward, ".2f"), without, *(_num(reference[c].get(w.k, math.nan), ".2f") for c in REWARD_COLUMNS),
                 _rate(w, "success"), " / ".join(_rate(w, o) for o in FAILURES), " / ".join(_num(x, ".2f") for x in stds),
                 val, _num(w.wall_s / 3600, ".2f")]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def compare_points(windows: list[Window], window: int) -> list[tuple[float, float, float]]:
    """What the figure draws of a compared run: (window centre, training reward without the
    prediction penalty, training success) for each finished window that logs the penalty
    throughout (a partly logged one would mix two quantities on one line)."""
    return [((w.k + 0.5) * window, w.reward_without_penalty, w.rates["success"])
            for w in windows if w.complete and w.episodes and w.split_share == 1]


def load_run(run: Path, window: int) -> tuple[list[dict], dict, list[Window]]:
    """A run folder's progress lines, settings and windows; a clear error for a folder without a log."""
    progress = run / "progress.jsonl"
    if not progress.exists():
        raise FileNotFoundError(f"{progress}: no such file")
    rows = read_progress(run)
    if not rows:
        raise ValueError(f"{progress}: no progress lines")
    settings = run_settings(run)
    return rows, settings, run_windows(rows, window, settings.get("env_steps"))


def figure(windows: list[Window], rows: list[dict], reference: dict[str, dict[int, float]], window: int,
           out: Path, x_max: int, title: str, val_episodes: int | None = None,
           others: list[tuple[str, list[Window]]] = ()) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    last = max(int(r["env_steps"]) for r in rows)
    if x_max <= 0:
        x_max = max(1, math.ceil(last / 1e6)) * 1_000_000
    centre = {w.k: (w.k + 0.5) * window if w.complete else (w.first_step + w.last_step) / 2 for w in windows}
    done = [w for w in windows if w.complete and w.episodes]
    partial = [w for w in windows if not w.complete and w.episodes]

    fig, (top, bottom, causes, spread) = plt.subplots(4, 1, figsize=(8, 10.4), sharex=True, height_ratios=(3, 2, 2, 2))
    for reward_c, entropy_c, label, colour in zip(REWARD_COLUMNS, ENTROPY_COLUMNS, ("reference (GST_predictor_rand)",
                                                  "reference (GST_predictor_non_rand)"), ("tab:gray", "black"), strict=True):
        for ax, c, f in ((top, reward_c, float), (spread, entropy_c, policy_std)):
            ks = [k for k in sorted(reference[c]) if k * window < x_max]
            ax.plot([(k + 0.5) * window for k in ks], [f(reference[c][k]) for k in ks], "-", color=colour, lw=1.2,
                    label=label)
    top.plot([centre[w.k] for w in done], [w.reward for w in done], "o-", color="tab:blue", label="this run")
    if partial:
        top.plot([centre[w.k] for w in partial], [w.reward for w in partial], "o", mfc="none", color="tab:blue",
                 label="this run, window so far")
    split = [w for w in done + partial if not math.isnan(w.reward_without_penalty)]
    if split:  # hollow: a window only part of which logs the penalty, or not finished
        top.plot([centre[w.k] for w in split], [w.reward_without_penalty for w in split], "--", color="tab:cyan",
                 label="this run without prediction penalty (as the reference logs)")
        for w in split:
            top.plot(centre[w.k], w.reward_without_penalty, "s", color="tab:cyan",
                     mfc="tab:cyan" if w.complete and w.split_share == 1 else "none")
    for (name, ws), colour in zip(others, itertools.cycle(COMPARE_COLOURS)):
        points = compare_points(ws, window)
        top.plot([x for x, _, _ in points], [r for _, r, _ in points], "^:", color=colour, ms=4,
                 label=f"{name} without prediction penalty")
        bottom.plot([x for x, _, _ in points], [100 * sr for _, _, sr in points], "^:", color=colour, ms=4,
                    label=f"{name}: training success")
    top.set_ylabel(f"training episode reward\n(mean per {window / 1e6:g} M env steps)")
    top.grid(alpha=0.3)
    top.legend(fontsize=8, loc="best")

    val = [(int(r["env_steps"]), r["val/success_rate"]) for r in rows if r.get("val/success_rate") is not None]
    ys = [100 * v for _, v in val]
    if val_episodes:  # 95 % Wilson intervals
        bounds = [rate_interval(v, val_episodes) for _, v in val]
        err = [[y - 100 * lo for y, (lo, _) in zip(ys, bounds, strict=True)],
               [100 * hi - y for y, (_, hi) in zip(ys, bounds, strict=True)]]
    bottom.errorbar([s for s, _ in val], ys, yerr=err if val_episodes else None, fmt="s-", color="tab:green",
                    capsize=2, label="validation success" + (f" ({val_episodes} episodes, 95 % CI)" if val_episodes else ""))
    for ws, style, mfc in ((done, "o-", None), (partial, "o", "none")):
        spread.plot([centre[w.k] for w in ws], [w.std for w in ws], style, mfc=mfc,
                    color="tab:blue", label="this run" if mfc is None else None)
    for ax, outcome, colour, label in ((bottom, "success", "tab:orange", "training success (per window)"),
                                       (causes, "human_collision", "tab:red", "human collision"),
                                       (causes, "wall_collision", "tab:brown", "wall collision"),
                                       (causes, "timeout", "tab:purple", "timeout")):
        ax.plot([centre[w.k] for w in done], [100 * w.rates[outcome] for w in done], "o-", color=colour, label=label)
        if partial:
            ax.plot([centre[w.k] for w in partial], [100 * w.rates[outcome] for w in partial], "o", mfc="none",
                    color=colour)
    bottom.set_ylabel("success (%)" if others else "this run: success (%)")
    causes.set_ylabel("this run: training\nepisodes ending in (%)")
    spread.set_ylabel("policy std (m/s)\n(geometric mean of vx, vy)")
    spread.set_xlabel("env steps")
    for ax in (bottom, causes, spread):
        ax.set_ylim(bottom=0)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, loc="upper left" if ax is bottom else ("upper right" if ax is causes else "lower left"))
    spread.set_xlim(0, x_max)
    spread.xaxis.set_major_formatter(matplotlib.ticker.FuncFormatter(lambda x, _: f"{x / 1e6:g} M" if x else "0"))
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=120)
    plt.close(fig)


def curve(cfg: CurveConfig) -> str | None:
    """Rebuild the reference CSV if asked, then write the run's figure and table; returns the table."""
    logs = (cfg.reference_rand_log, cfg.reference_non_rand_log)
    if any(logs):
        if not all(logs):
            raise ValueError("--reference_rand_log and --reference_non_rand_log go together")
        for log in logs:
            if not Path(log).exists():
                raise FileNotFoundError(f"{log}: no such file")
        rows = write_reference(Path(logs[0]), Path(logs[1]), Path(cfg.reference), cfg.window)
        print(f"wrote {cfg.reference} ({len(rows)} windows of {cfg.window:,} env steps)")
    if cfg.run is None:
        if not any(logs):
            raise ValueError("give --run=DIR (a folder with progress.jsonl), or the two reference logs")
        return None
    rows, settings, windows = load_run(Path(cfg.run), cfg.window)
    others = [(Path(o).resolve().name, load_run(Path(o), cfg.window)[2]) for o in cfg.compare]
    reference = read_reference(Path(cfg.reference), cfg.window)
    episodes = settings.get("val", {}).get("n_episodes")
    text = table(windows, reference, cfg.window, episodes)
    print(text)
    if cfg.output_md:
        Path(cfg.output_md).parent.mkdir(parents=True, exist_ok=True)
        Path(cfg.output_md).write_text(text + "\n")
    if cfg.output_png is not None:
        last = max(rows, key=lambda r: int(r["env_steps"]))
        walls = [r["time/wall_s"] for r in rows if r.get("time/wall_s") is not None]
        title = cfg.title or (f"{Path(cfg.run).resolve().name}: {int(last['env_steps']):,} env steps"
                              + (f", {max(walls) / 3600:.1f} h of training" if walls else ""))
        figure(windows, rows, reference, cfg.window, Path(cfg.output_png), cfg.x_max, title, episodes, others)
    return text


def main(argv: list[str] | None = None) -> None:
    run_cli(CurveConfig, curve, argv)


if __name__ == "__main__":
    main()
