"""Simulator configuration: one dataclass, two presets, and the episode-seed splits.

Every number that comes from a paper lives here, once, with its source:
- ``paper``: the PDPO paper's setting (its table of simulation parameters).
- ``crowdnavpp``: the defaults of the CrowdNav++ repository (Liu et al., ICRA 2023,
  ``crowd_nav/configs/config.py``; env ``CrowdSimPred-v0``).

A field left at ``None`` takes the preset's value; :meth:`CrowdSimConfig.resolve` returns the
concrete configuration that the simulator uses and that results are saved with.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

from .. import layout

TASKS = ("CrowdNav-v0", "BoundedCrowdNav-v0")
ORCA_ROBOTS = ("look_ahead", "current_state")
"""The two ORCA robots of CrowdNav++ (docs/simulator.md, "The ORCA robot"). ``look_ahead``
(``CrowdSimPred``, the env the paper builds on): every human visible at the last observation is
seen at its true position now and 1..L steps ahead (the humans' ORCA roll-out), L + 1 agents per
human. ``current_state`` (``CrowdSimVarNum``, CrowdNav++'s published ORCA baseline): one agent per
human from the robot's memory, last observed state, extrapolated while out of sight, a dummy far
away until first seen."""
"""``CrowdNav-v0``: the original benchmark, no boundary. ``BoundedCrowdNav-v0``: walls on the
boundary of the ``[-arena_size, arena_size]^2`` workspace; touching one is a collision."""
HUMAN_POLICIES = ("orca", "social_force")
"""The humans' policies of CrowdNav++ (``humans.policy``; docs/simulator.md, "Crowd models").
``orca``: RVO2 with every other human as an agent (the benchmark's crowd). ``social_force``:
CrowdNav++'s ``SOCIAL_FORCE`` policy, a goal pull and exponential repulsion from every other agent
(``sf.A``, ``sf.B``, ``sf.KI``)."""
CROWDS: dict[str, dict] = {
    "orca": dict(robot_visible=False, human_policy="orca"),
    "reactive_orca": dict(robot_visible=True, human_policy="orca"),
    "social_force": dict(robot_visible=False, human_policy="social_force"),
    "reactive_social_force": dict(robot_visible=True, human_policy="social_force"),
}
"""The four crowd settings of the generalization table and the benchmark (docs/simulator.md,
"Crowd models"): ``orca`` is the benchmark's crowd, the one every shipped policy was trained in;
the others are crowds they never saw (the env fields each one sets)."""

_COMMON = dict(
    num_humans=20,  # both: 20 humans, fixed count
    arena_size=6.0,  # both: 12 x 12 m workspace, robot start/goal ~ U(-6, 6)^2
    robot_v_pref=1.0,  # both: robot max speed (m/s)
    robot_min_start_goal_dist=8.0,  # CrowdNav++ generate_robot: |start - goal| >= 8
    # Not in either source: start/goal ~ U(-(arena - margin), arena - margin). With 0 (faithful),
    # a Bounded episode whose start lies within one robot radius of a wall is a wall collision at
    # its first step (about 1 in 9 episodes with the paper preset).
    robot_spawn_margin=0.0,
    human_radius=0.3,  # CrowdNav++ humans.radius (used when attributes are not randomized)
    human_v_pref=1.0,  # CrowdNav++ humans.v_pref
    human_radius_range=(0.3, 0.5),  # CrowdNav++ sample_random_attributes
    human_v_pref_range=(0.5, 1.5),
    circle_radius=6.0 * math.sqrt(2.0),  # CrowdNav++ sim.circle_radius: circle through the corners
    start_noise=2.0,  # CrowdNav++ CrowdSimVarNum noise_range: start noise U(0,1)*2, not centred
    dt=0.25,  # control interval (s)
    time_limit=50.0,  # episode time limit (s); timeout fires at t >= time_limit - 1
    prediction_steps=5,  # constant-velocity prediction horizon L (steps)
    goal_change_prob=0.5,  # CrowdNav++ goal_change_chance
    discomfort_dist=0.25,  # CrowdNav++ reward.discomfort_dist (m)
    # ORCA (CrowdNav++ config.orca, RVO2 parameters), for humans and the ORCA robot.
    orca_neighbor_dist=10.0,
    orca_time_horizon=5.0,
    orca_time_horizon_obst=5.0,
    orca_safety_space=0.15,  # added to every ORCA radius, with the 0.01 pad below
    orca_radius_pad=0.01,
    # (CrowdNav++ gives the other agents max speed 1; it never enters agent 0's solve, so no field.)
    # CrowdNav++ Agent.__init__: with randomize_attributes, every new human redraws the one shared
    # config.orca.neighbor_dist from U(5, 10) (see randomize_neighbor_dist).
    neighbor_dist_range=(5.0, 10.0),
    # CrowdNav++'s ORCA policy knows no obstacles: the robot ignores the walls (they only end its
    # episodes); the paper's Bounded ORCA row is this robot.
    orca_robot_wall_aware=False,
    # Crowd models (CrowdNav++ config.robot.visible, config.humans.policy, config.sf). The paper's
    # crowd ignores the robot and follows ORCA; the other settings measure trained policies in
    # crowds they were not trained in (docs/simulator.md, "Crowd models").
    robot_visible=False,  # robot.visible: humans' ORCA / social force counts the robot as an agent
    human_policy="orca",  # humans.policy: orca | social_force
    sf_a=2.0,  # sf.A: repulsion strength (m/s^2 at contact)
    sf_b=1.0,  # sf.B: repulsion range (m)
    sf_ki=1.0,  # sf.KI: inverse relaxation time toward the desired velocity (1/s)
    # Reward (CrowdNav++ config.reward and CrowdSimPred.calc_reward).
    success_reward=10.0,
    collision_penalty=-20.0,
    discomfort_penalty_factor=10.0,
    potential_factor=2.0,  # holonomic robot
    prediction_radius=0.3,  # humans.radius in the prediction penalty and the intrusion test
    sentinel=layout.SENTINEL,  # observation value of invisible-human rows (15)
)

PRESETS: dict[str, dict] = {
    "paper": dict(
        _COMMON,
        robot_radius=0.2,
        sensing_range=6.0,
        randomize_attributes=True,  # paper: r ~ U(0.3, 0.5), v_pref ~ U(0.5, 1.5) per human
        goal_change_interval=1.0,  # paper text: every 1 s
        orca_robot="look_ahead",  # the paper builds on CrowdSimPred (constant-velocity predictor)
        randomize_neighbor_dist=False,  # not in the paper
        # Off: on, its Bounded ORCA row reads 51-55 % (the paper: 47.0; off: 49.0; docs/simulator.md).
        persistent_orca_sims=False,
    ),
    "crowdnavpp": dict(
        _COMMON,
        robot_radius=0.3,
        sensing_range=5.0,
        randomize_attributes=True,  # config.env.randomize_attributes (its ORCA baseline: False)
        goal_change_interval=5.0,  # the code: `global_time % 5 == 0`
        orca_robot="current_state",  # CrowdSimVarNum: the env of CrowdNav++'s ORCA baseline
        randomize_neighbor_dist=None,  # the code: on exactly when randomize_attributes is
        persistent_orca_sims=None,  # the code: always; it matters only when randomize_attributes
    ),
}


@dataclass
class CrowdSimConfig:
    """Crowd simulator settings. Units: metres, seconds, m/s.

    ``task`` picks the variant (see :data:`TASKS`), ``preset`` the defaults; every other field
    overrides its preset value when set. ``compute_intrusion`` turns on the ITR/SD intrusion test
    (a 5-step ORCA look-ahead of the humans each step, about 5x the humans' cost): on for
    evaluation, off for fast training rollouts.
    """

    # Variant: CrowdNav-v0 (original, no boundary) or BoundedCrowdNav-v0 (walls; touching = collision).
    task: str = "BoundedCrowdNav-v0"
    # Defaults for every unset field: paper (PDPO paper) or crowdnavpp (CrowdNav++ repository).
    preset: str = "paper"
    # Intrusion test for ITR/SD (5-step ORCA look-ahead of the humans); off for fast training.
    compute_intrusion: bool = True
    # Number of humans (both presets: 20).
    num_humans: int | None = None
    # Half side of the square workspace, m (6: a 12 x 12 m arena).
    arena_size: float | None = None
    # Robot radius, m (paper 0.2, crowdnavpp 0.3).
    robot_radius: float | None = None
    # Robot max speed, m/s; actions are clipped to this norm (1.0).
    robot_v_pref: float | None = None
    # Minimum robot start-goal distance, m (8).
    robot_min_start_goal_dist: float | None = None
    # Sample robot start/goal in [-(arena - margin), arena - margin]^2, m (0: faithful).
    robot_spawn_margin: float | None = None
    # Sensing range on surface distance, m (paper 6, crowdnavpp 5).
    sensing_range: float | None = None
    # Per-human radius ~ human_radius_range, v_pref ~ human_v_pref_range (both presets: true).
    randomize_attributes: bool | None = None
    # Human radius when not randomized, m (0.3).
    human_radius: float | None = None
    # Human max speed when not randomized, m/s (1.0).
    human_v_pref: float | None = None
    # Range of randomized human radii, m ([0.3, 0.5]).
    human_radius_range: tuple[float, float] | None = None
    # Range of randomized human max speeds, m/s ([0.5, 1.5]).
    human_v_pref_range: tuple[float, float] | None = None
    # Radius of the circle humans start and aim on, m (6 sqrt(2), through the corners).
    circle_radius: float | None = None
    # Human start noise U(0, 1) * start_noise added to each coordinate, m (2).
    start_noise: float | None = None
    # Control interval, s (0.25).
    dt: float | None = None
    # Episode time limit, s (50; the timeout fires at t >= time_limit - 1, the 197th step).
    time_limit: float | None = None
    # Constant-velocity prediction horizon L, steps (5).
    prediction_steps: int | None = None
    # Period of random human goal changes, s (paper 1, crowdnavpp 5).
    goal_change_interval: float | None = None
    # Probability that a human changes goal at each goal-change time (0.5; 0 turns goal changes
    # off, as humans.random_goal_changing = False in CrowdNav++'s ORCA-baseline config).
    goal_change_prob: float | None = None
    # Discomfort distance on surface distance, m (0.25).
    discomfort_dist: float | None = None
    # ORCA neighbour distance, m (10).
    orca_neighbor_dist: float | None = None
    # ORCA robot: look_ahead (sees visible humans now and 1..L steps ahead, CrowdSimPred; paper
    # default) or current_state (sees its memory of each human, CrowdSimVarNum; crowdnavpp default).
    orca_robot: str | None = None
    # ORCA robot avoids the Bounded walls as RVO2 static obstacles (false: CrowdNav++'s robot,
    # which ignores them; true: a stronger baseline / demonstrator).
    orca_robot_wall_aware: bool | None = None
    # CrowdNav++ quirk: each new human (reset, respawn) redraws the env's shared ORCA neighbour
    # distance from neighbor_dist_range (crowdnavpp: = randomize_attributes; paper: false).
    randomize_neighbor_dist: bool | None = None
    # Range of the redrawn neighbour distance, m ([5, 10]).
    neighbor_dist_range: tuple[float, float] | None = None
    # CrowdNav++ quirk: every ORCA policy keeps the RVO2 simulator of its first call and only moves
    # its agents, so the ORCA robot uses the humans' radii (0.3 for those it had not seen) and the
    # neighbour distance of a first observation in another episode (here: episode seed + 1's), and
    # each human those of its creation (a respawned neighbour keeps its old radius). Changes the
    # crowd for every policy. crowdnavpp: = randomize_attributes; paper: false.
    persistent_orca_sims: bool | None = None
    # Humans react to the robot: their ORCA (or social force) counts it as an agent with its
    # radius and current velocity (CrowdNav++ robot.visible; both presets: false, the paper's crowd).
    robot_visible: bool | None = None
    # The humans' policy: orca (both presets; the benchmark's crowd) or social_force (CrowdNav++'s
    # SOCIAL_FORCE, parameters sf_a, sf_b, sf_ki): a crowd the shipped policies were not trained in.
    human_policy: str | None = None
    # Social force: repulsion strength A, m/s^2 at contact (CrowdNav++ sf.A = 2).
    sf_a: float | None = None
    # Social force: repulsion range B, m (CrowdNav++ sf.B = 1).
    sf_b: float | None = None
    # Social force: goal-pull gain KI = 1 / relaxation time, 1/s (CrowdNav++ sf.KI = 1).
    sf_ki: float | None = None
    # ORCA time horizon for agents, s (5).
    orca_time_horizon: float | None = None
    # ORCA time horizon for obstacles (walls, ORCA robot only), s (5).
    orca_time_horizon_obst: float | None = None
    # Safety space added to every ORCA radius, m (0.15).
    orca_safety_space: float | None = None
    # Extra pad added to every ORCA radius, m (0.01).
    orca_radius_pad: float | None = None
    # Reward for reaching the goal (10).
    success_reward: float | None = None
    # Reward for a human or wall collision; also scales the prediction penalty (-20).
    collision_penalty: float | None = None
    # Discomfort reward factor: (dmin - discomfort_dist) * factor * dt (10).
    discomfort_penalty_factor: float | None = None
    # Potential (progress) reward factor (2).
    potential_factor: float | None = None
    # Human radius used by the prediction penalty and the intrusion test, m (0.3).
    prediction_radius: float | None = None
    # Observation value of the rows of invisible humans (15).
    sentinel: float | None = None

    @property
    def bounded(self) -> bool:
        return self.task == "BoundedCrowdNav-v0"

    @property
    def orca_description(self) -> str:
        """Which ORCA robot this env runs, e.g. ``orca (look_ahead)`` (resolved configs only)."""
        walls = ", wall-aware" if self.orca_robot_wall_aware and self.bounded else ""
        return f"orca ({self.orca_robot}{walls})"

    @property
    def crowd_description(self) -> str:
        """The crowd model, e.g. ``ORCA humans, robot invisible`` (resolved configs only)."""
        policy = {"orca": "ORCA", "social_force": "social-force"}.get(self.human_policy, self.human_policy)
        return f"{policy} humans, robot {'visible' if self.robot_visible else 'invisible'}"

    def resolve(self) -> CrowdSimConfig:
        """A copy with every ``None`` replaced by the preset value, validated."""
        if self.task not in TASKS:
            raise ValueError(f"unknown task {self.task!r}; choose one of {', '.join(TASKS)}")
        if self.preset not in PRESETS:
            raise ValueError(f"unknown preset {self.preset!r}; choose one of {', '.join(PRESETS)}")
        preset = PRESETS[self.preset]
        values = {}
        for f in dataclasses.fields(CrowdSimConfig):
            v = getattr(self, f.name)
            values[f.name] = preset[f.name] if v is None else v
        for quirk in ("randomize_neighbor_dist", "persistent_orca_sims"):  # crowdnavpp: they come
            if values[quirk] is None:  # with randomization
                values[quirk] = values["randomize_attributes"]
        for key in ("human_radius_range", "human_v_pref_range", "neighbor_dist_range"):
            values[key] = tuple(float(x) for x in values[key])
        cfg = CrowdSimConfig(**values)
        cfg._validate()
        return cfg

    def _validate(self) -> None:
        positive = ("arena_size", "robot_radius", "robot_v_pref", "sensing_range", "human_radius",
                    "human_v_pref", "circle_radius", "dt", "time_limit", "goal_change_interval",
                    "orca_neighbor_dist", "orca_time_horizon", "orca_time_horizon_obst")
        for name in positive:
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        if self.num_humans < 1:
            raise ValueError(f"num_humans must be >= 1, got {self.num_humans}")
        if self.prediction_steps < 1:
            raise ValueError(f"prediction_steps must be >= 1, got {self.prediction_steps}")
        if not 0.0 <= self.goal_change_prob <= 1.0:
            raise ValueError(f"goal_change_prob must be in [0, 1], got {self.goal_change_prob}")
        if self.orca_robot not in ORCA_ROBOTS:
            raise ValueError(f"unknown orca_robot {self.orca_robot!r}; choose one of {', '.join(ORCA_ROBOTS)}")
        if self.human_policy not in HUMAN_POLICIES:
            raise ValueError(f"unknown human_policy {self.human_policy!r}; choose one of {', '.join(HUMAN_POLICIES)}")
        if self.robot_visible not in (True, False):
            raise ValueError(f"robot_visible must be true or false, got {self.robot_visible!r}")
        for name in ("sf_a", "sf_ki"):
            if not (math.isfinite(getattr(self, name)) and getattr(self, name) >= 0):
                raise ValueError(f"{name} must be a finite number >= 0, got {getattr(self, name)}")
        if not (math.isfinite(self.sf_b) and self.sf_b > 0):
            raise ValueError(f"sf_b (the social-force range, m) must be > 0, got {self.sf_b}")
        for name in ("human_radius_range", "human_v_pref_range", "neighbor_dist_range"):
            lo, hi = getattr(self, name)
            if not 0 < lo <= hi:
                raise ValueError(f"{name} must satisfy 0 < low <= high, got {(lo, hi)}")
        steps = self.goal_change_interval / self.dt
        if abs(steps - round(steps)) > 1e-9:
            raise ValueError("goal_change_interval must be a multiple of dt")
        if not 0 <= self.robot_spawn_margin < self.arena_size:
            raise ValueError(f"robot_spawn_margin must be in [0, arena_size), got {self.robot_spawn_margin}")
        if self.robot_min_start_goal_dist >= 2 * math.sqrt(2) * (self.arena_size - self.robot_spawn_margin):
            raise ValueError("robot_min_start_goal_dist cannot be met inside the arena")

    # Derived quantities, in steps.
    @property
    def max_steps(self) -> int:
        """Steps of an episode that times out: the timeout fires once t >= time_limit - 1."""
        return int(math.ceil((self.time_limit - 1.0) / self.dt - 1e-9)) + 1

    @property
    def goal_change_every(self) -> int:
        return int(round(self.goal_change_interval / self.dt))

    @property
    def obs_dim(self) -> int:
        return layout.obs_dim(self.num_humans, self.prediction_steps)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


# Episode seeds. One seed = one episode, bitwise identical whatever the batch size or slot.
SEED_SPLITS: dict[str, tuple[int, int]] = {
    "train": (0, 1_000_000_000),  # [0, 1e9): demonstrations (from 0) and the learners' blocks below
    "val": (1_000_000_000, 1_000_001_000),  # checkpoint and recipe selection (up to 1,000 episodes)
    "test": (2_000_000_000, 2_000_000_500),  # 500 episodes: every reported table
    # Never used to choose or report: whether a target met on the test seeds holds on fresh episodes.
    "holdout": (3_000_000_000, 3_000_010_000),
}
# The learners' blocks of train seeds, apart from the demonstrations' (ORCA, from seed 0):
PPO_ENV_SEED = 500_000_000  # PPO rollouts: process r of a run from PPO_ENV_SEED + r * PPO_PROCESS_SEEDS
PPO_PROCESS_SEEDS = 10_000_000
PPO_STAGE2_ENV_SEED = 520_000_000  # the main job's second fine-tuning stage (after 2 processes' blocks)
DAGGER_SEED_BASE = 800_000_000  # DAgger learner episodes of round r: from DAGGER_SEED_BASE + r * DAGGER_ROUND_SEEDS
DAGGER_ROUND_SEEDS = 1_000_000


def split_seeds(split: str, n: int | None = None, offset: int = 0) -> list[int]:
    """The first ``n`` seeds (all if ``None``) of a split, starting ``offset`` into it."""
    if split not in SEED_SPLITS:
        raise ValueError(f"unknown split {split!r}; choose one of {', '.join(SEED_SPLITS)}")
    lo, hi = SEED_SPLITS[split]
    size = hi - lo
    n = size - offset if n is None else n
    if n < 0 or offset < 0 or offset + n > size:
        raise ValueError(f"split {split!r} has {size} seeds; asked for {n} from offset {offset}")
    return list(range(lo + offset, lo + offset + n))
