"""Navigation metrics from per-episode records (the episode records of ``CrowdNavVectorEnv``).

- SR, CR (human + wall), TR: shares of episodes ending in success, collision, timeout.
- NT (s): mean navigation time of successful episodes, ``(length - 1) * dt``: the time of the
  pre-move position found at the goal, which CrowdNav++'s evaluation records (``global_time``
  read before the final step).
- PL (m): mean robot path length per episode, summed over the robot's own moves up to the
  final step's pre-move position (where NT stops). CrowdNav++'s evaluation replaces the final
  move with the jump to the next episode's start position (its vectorised env has already reset
  when the length is read); this one does not.
- ITR: per episode, the share of steps in which the robot is within ``r + 0.3`` of a visible
  human's true position 1..5 steps ahead; averaged over episodes (a fraction; tables show %). As
  in CrowdNav++, the step that ends the episode is never an intrusion but counts in the steps.
- SD (m): mean over all intrusion steps of all episodes of the closest such centre distance.
- OOB: share of successful episodes whose robot centre left the workspace at some step.

``outcome`` splits Bounded wall collisions by cause for the report's wall audit.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

from ..sim.engine import EVENT_NAMES, HUMAN_COLLISION, SUCCESS, TIMEOUT, WALL_COLLISION

# The metric definitions' version, saved with every evaluation: one saved under another is run
# again, not reused (2: NT and ITR as CrowdNav++ counts them, 2026-11-28).
METRICS_VERSION = 2


@dataclass
class EpisodeRecord:
    seed: int
    event: str  # success | human_collision | wall_collision | timeout
    steps: int
    path_length: float  # m
    intrusion_steps: int
    intrusion_distance_sum: float  # m, over intrusion steps
    out_of_bounds: bool
    episode_return: float
    goal: tuple[float, float] | None = None  # the robot's goal (m, world frame); None in older records

    @classmethod
    def from_final_info(cls, final_info: dict, b: int) -> EpisodeRecord:
        return cls(
            seed=int(final_info["seed"][b]),
            event=EVENT_NAMES[int(final_info["event"][b])],
            steps=int(final_info["length"][b]),
            path_length=float(final_info["path_length"][b]),
            intrusion_steps=int(final_info["intrusion_steps"][b]),
            intrusion_distance_sum=float(final_info["intrusion_distance_sum"][b]),
            out_of_bounds=bool(final_info["out_of_bounds"][b]),
            episode_return=float(final_info["return"][b]),
            goal=(float(final_info["goal"][b, 0]), float(final_info["goal"][b, 1])) if "goal" in final_info else None,
        )

    def to_dict(self) -> dict:
        return asdict(self)


# The episode events (sim/engine.EVENT_NAMES), wall collisions split by cause.
OUTCOMES = (EVENT_NAMES[SUCCESS], EVENT_NAMES[HUMAN_COLLISION], "wall_at_start", "wall_goal_in_zone", "wall_other",
            EVENT_NAMES[TIMEOUT])


def outcome(record: dict, arena_size: float, robot_radius: float) -> str | None:
    """How an episode (a record as in ``metrics.json``) ended, one of ``OUTCOMES``; Bounded wall
    collisions split by cause:

    - ``wall_at_start``: on the first step, whose check sees the start position: the robot
      starts touching a wall (CrowdNav++ draws it anywhere in the square), and no policy avoids it;
    - ``wall_goal_in_zone``: later, with the goal inside the wall zone (``goal_in_wall_zone``):
      reaching it (within r) takes a stop in a band narrower than r between the zone and the goal;
    - ``wall_other``: any other wall collision.

    None for a later wall collision in a record without its goal (written before goals were kept)."""
    event = record["event"]
    if event != EVENT_NAMES[WALL_COLLISION]:
        return event
    if record["steps"] == 1:
        return "wall_at_start"
    if record.get("goal") is None:
        return None
    return "wall_goal_in_zone" if goal_in_wall_zone(record["goal"], arena_size, robot_radius) else "wall_other"


def goal_in_wall_zone(goal, arena_size: float, robot_radius: float) -> bool:
    """Whether a robot centre at ``goal`` (m) would touch a Bounded wall."""
    return max(abs(goal[0]), abs(goal[1])) >= arena_size - robot_radius


def wilson_interval(successes: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """The 95 % (z = 1.96) Wilson score interval of a success rate: unlike the normal
    approximation it stays inside [0, 1] and keeps its coverage near 0 % and 100 %."""
    if n < 1:
        return math.nan, math.nan
    p = successes / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z / (1 + z * z / n) * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n))
    return max(0.0, centre - half), min(1.0, centre + half)


def rate_interval(rate: float, n: int) -> tuple[float, float]:
    """The 95 % Wilson interval of a success rate read on ``n`` episodes (a metrics file's or a
    progress record's ``sr``, which keeps the rate, not the count)."""
    return wilson_interval(round(rate * n), n)


def _mean(values) -> float:
    values = list(values)
    return sum(values) / len(values) if values else math.nan


def compute_metrics(records: list[EpisodeRecord], dt: float) -> dict[str, float]:
    """Aggregate metrics; rates are fractions in [0, 1], times in s, distances in m.

    A mean over an empty set (NT with no success, SD with no intrusion) is NaN.
    """
    if not records:
        raise ValueError("no episodes to aggregate")
    n = len(records)
    success = [r for r in records if r.event == EVENT_NAMES[SUCCESS]]
    count = {code: sum(r.event == EVENT_NAMES[code] for r in records)
             for code in (SUCCESS, HUMAN_COLLISION, WALL_COLLISION, TIMEOUT)}
    intrusion_steps = sum(r.intrusion_steps for r in records)
    return {
        "sr": count[SUCCESS] / n,
        "cr": (count[HUMAN_COLLISION] + count[WALL_COLLISION]) / n,
        "cr_human": count[HUMAN_COLLISION] / n,
        "cr_wall": count[WALL_COLLISION] / n,
        "tr": count[TIMEOUT] / n,
        "nt": _mean((r.steps - 1) * dt for r in success),
        "pl": _mean(r.path_length for r in records),
        "itr": _mean(r.intrusion_steps / r.steps for r in records),
        "sd": (sum(r.intrusion_distance_sum for r in records) / intrusion_steps
               if intrusion_steps else math.nan),
        "oob": _mean(float(r.out_of_bounds) for r in success),
        "mean_return": _mean(r.episode_return for r in records),
    }


def _fmt(value: float, digits: int = 2) -> str:
    return "n/a" if math.isnan(value) else f"{value:.{digits}f}"


def table_columns(bounded: bool) -> list[str]:
    base = ["SR", "NT", "PL", "ITR", "SD"]
    return base if bounded else base + ["CR", "TR", "OOB"]


def markdown_row(metrics: dict[str, float], bounded: bool, name: str | None = None) -> str:
    """``| SR | NT | PL | ITR | SD |`` (+ CR, TR, OOB for the original variant); rates in %.
    ``metrics`` as computed or as read back from a ``metrics.json`` (undefined means saved as null)."""
    metrics = {k: math.nan if v is None else v for k, v in metrics.items()}
    cells = {
        "SR": _fmt(100 * metrics["sr"], 1), "NT": _fmt(metrics["nt"]), "PL": _fmt(metrics["pl"]),
        "ITR": _fmt(100 * metrics["itr"]), "SD": _fmt(metrics["sd"]),
        "CR": _fmt(100 * metrics["cr"], 1), "TR": _fmt(100 * metrics["tr"], 1),
        "OOB": _fmt(100 * metrics["oob"], 1),
    }
    values = ([name] if name is not None else []) + [cells[c] for c in table_columns(bounded)]
    return "| " + " | ".join(values) + " |"


def markdown_header(bounded: bool, name: str | None = None) -> str:
    cols = ([name] if name is not None else []) + [
        {"SR": "SR (%)", "NT": "NT (s)", "PL": "PL (m)", "ITR": "ITR (%)", "SD": "SD (m)",
         "CR": "CR (%)", "TR": "TR (%)", "OOB": "OOB (%)"}[c] for c in table_columns(bounded)]
    return "| " + " | ".join(cols) + " |\n|" + "---|" * len(cols)
