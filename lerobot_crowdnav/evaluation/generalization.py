"""The crowd-generalization table, one place for everything that makes it: the crowds it names
(``sim.config.CROWDS``), how a policy is evaluated under one (env fields, CLI flags, result
folder), and the table itself, as CSV and markdown. ``lerobot-crowdnav-baselines
--only='[generalization]'`` (``evaluation/baselines.py``), the main job's report
(``evaluation/report.py``, fed by ``main/evaluation.py``) and ``make tables``
(``evaluation/tables.py``, from ``docs/data/main/generalization_<task>.csv``) all use it.

One table per benchmark: a row per policy, for each crowd its SR (%) with the 95 % Wilson
interval over its test episodes (every seed's pooled), the change of SR from the trained crowd
(the first crowd, ``orca``: the one every policy was trained in), and where the other episodes
went: human collisions, wall collisions (Bounded only) and timeouts, in % of the episodes.

The CSV (:func:`generalization_csv`) has one line per (policy, crowd), means and stds over the
training seeds in scaled units (% for rates, s for NT); the markdown (:func:`generalization_markdown`)
is written from the CSV's lines, so a table in the docs is exactly the report's.
"""

from __future__ import annotations

import csv
import io
import math
from pathlib import Path

from ..measure.metrics import wilson_interval
from ..sim.config import CROWDS

TRAINED = "orca"  # the crowd every shipped or trained policy was trained in: the reference of "SR change"
CROWD_LABELS = {"orca": "trained (ORCA)", "reactive_orca": "reactive ORCA", "social_force": "social force",
                "reactive_social_force": "reactive social force"}
# CSV column -> (metrics key, scale): mean and std over the seeds of each (policy, crowd).
_MEASURES = {"SR": ("sr", 100.0), "CR_human": ("cr_human", 100.0), "CR_wall": ("cr_wall", 100.0),
             "TR": ("tr", 100.0), "NT": ("nt", 1.0), "ITR": ("itr", 100.0)}
CSV_COLUMNS = ["method", "crowd", "n_seeds", "n_episodes", "SR_mean", "SR_std", "SR95_low", "SR95_high", "SR_change",
               *(f"{m}_{s}" for m in list(_MEASURES)[1:] for s in ("mean", "std"))]


# -- the crowds ----------------------------------------------------------------------------------
def check_crowds(crowds: list[str], flag: str = "--crowds", allow_empty: bool = False) -> None:
    """One clear error for a crowd name that is not in ``CROWDS`` (or an empty list, unless allowed)."""
    bad = [c for c in crowds if c not in CROWDS]
    if bad or (not crowds and not allow_empty) or len(set(crowds)) != len(crowds):
        raise ValueError(f"{flag} must list distinct crowds among {', '.join(CROWDS)}, got {list(crowds)}"
                         + (f" (unknown: {', '.join(bad)})" if bad else ""))


def crowd_env(crowd: str) -> dict:
    """The simulator fields that make ``crowd`` (``CrowdSimConfig(**env, **crowd_env(crowd))``)."""
    return dict(CROWDS[crowd])


def crowd_flags(crowd: str) -> list[str]:
    """The same as ``lerobot-crowdnav-eval`` flags, e.g. ``--env.robot_visible=true``."""
    return [f"--env.{k}={str(v).lower() if isinstance(v, bool) else v}" for k, v in CROWDS[crowd].items()]


def crowd_dir(eval_dir: Path, crowd: str) -> Path:
    """Where a policy's evaluation under ``crowd`` goes, next to its trained-crowd ``eval_dir``:
    that directory itself for the trained crowd, ``<eval_dir>_<crowd>`` for the others."""
    eval_dir = Path(eval_dir)
    return eval_dir if crowd == TRAINED else eval_dir.with_name(f"{eval_dir.name}_{crowd}")


def crowds_sentence(crowds: list[str]) -> str:
    """The crowds and the fields that make each, for a caption."""
    return "; ".join(f"{CROWD_LABELS[c]}: `{', '.join(f'{k}={v}' for k, v in CROWDS[c].items())}`" for c in crowds)


# -- the table -----------------------------------------------------------------------------------
def _stats(values: list) -> tuple[float, float]:
    vals = [float(v) for v in values if v is not None and not math.isnan(float(v))]
    if not vals:
        return math.nan, math.nan
    mean = sum(vals) / len(vals)
    return mean, math.sqrt(sum((v - mean) ** 2 for v in vals) / len(vals))


def _num(value: float) -> str:
    return "" if math.isnan(value) else f"{value:.6g}"


def generalization_csv(results: dict[str, dict[str, list[dict]]], crowds: list[str]) -> str:
    """``results``: row label -> crowd -> the metrics (``metrics.json``) of each training seed;
    ``crowds`` in column order, the first the reference of ``SR_change`` (SR points)."""
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(CSV_COLUMNS)
    for label, by_crowd in results.items():
        reference = _stats([m["sr"] for m in by_crowd[crowds[0]]])[0] * 100.0
        for crowd in crowds:
            metrics = by_crowd[crowd]
            counts = [(round(m["sr"] * m["n_episodes"]), m["n_episodes"]) for m in metrics]
            lo, hi = (100.0 * v for v in wilson_interval(sum(k for k, _ in counts), sum(n for _, n in counts)))
            sr, sr_std = (100.0 * v for v in _stats([m["sr"] for m in metrics]))
            change = "" if crowd == crowds[0] else _num(sr - reference)
            cells = []
            for name, (key, scale) in list(_MEASURES.items())[1:]:
                mean, std = _stats([m.get(key) for m in metrics])
                cells += [_num(scale * mean), _num(scale * std)]
            writer.writerow([label, crowd, len(metrics), sum(n for _, n in counts), _num(sr), _num(sr_std),
                             _num(lo), _num(hi), change, *cells])
    return buf.getvalue()


def read_csv(text: str) -> list[dict[str, str]]:
    return list(csv.DictReader(io.StringIO(text)))


def _cell(value: str, digits: int = 1) -> str:
    return "n/a" if value == "" else f"{float(value):.{digits}f}"


def generalization_markdown(rows: list[dict[str, str]], bounded: bool, first: str = "Method") -> str:
    """The markdown table of :func:`generalization_csv`'s lines (parsed, :func:`read_csv`): a row
    per policy; per crowd, SR (%) with its 95 % interval (``mean ± std`` over several seeds), the
    change from the reference crowd (SR points; not for the reference itself) and the split of
    the rest, human CR / wall CR (Bounded) / TR in %."""
    crowds = list(dict.fromkeys(r["crowd"] for r in rows))
    by_label: dict[str, dict[str, dict[str, str]]] = {}
    for r in rows:
        by_label.setdefault(r["method"], {})[r["crowd"]] = r
    split = "human CR / wall CR / TR (%)" if bounded else "human CR / TR (%)"
    header = [first]
    for i, crowd in enumerate(crowds):
        name = CROWD_LABELS.get(crowd, crowd)
        header += [f"{name}: SR (%) [95 % CI]", *([f"{name}: SR change"] if i else []), f"{name}: {split}"]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for label, by_crowd in by_label.items():
        cells = [label]
        for i, crowd in enumerate(crowds):
            r = by_crowd.get(crowd)
            if r is None:  # not evaluated under this crowd
                cells += ["-"] * (3 if i else 2)
                continue
            sr = _cell(r["SR_mean"]) + (f" ± {_cell(r['SR_std'])}" if int(r["n_seeds"]) > 1 else "")
            if r["SR95_low"] != "":
                sr += f" [{_cell(r['SR95_low'])}, {_cell(r['SR95_high'])}]"
            cells.append(sr)
            if i:
                cells.append("n/a" if r["SR_change"] == "" else f"{float(r['SR_change']):+.1f}")
            parts = [r["CR_human_mean"], *([r["CR_wall_mean"]] if bounded else []), r["TR_mean"]]
            cells.append(" / ".join(_cell(p) for p in parts))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)
