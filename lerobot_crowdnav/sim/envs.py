"""Gymnasium environments over the batched simulator.

``CrowdNavEnv`` (single environment) and ``CrowdNavVectorEnv`` (native batch with same-step
autoreset), registered as ``lerobot_crowdnav/CrowdNav-v0`` (original benchmark, no boundary) and
``lerobot_crowdnav/BoundedCrowdNav-v0`` (walls on the workspace boundary).

Observation
    ``Box(269,) float32``: ``[robot 7 | robot velocity 2 | humans 20 x 12 | mask 20]``.
    robot = ``px, py, radius, gx, gy, v_pref, theta`` (world frame, m; theta stays pi/2);
    velocity = last executed ``vx, vy`` (m/s); each human row = ``x_k, y_k`` for k = 0..5: current
    and constant-velocity predicted positions (dt = 0.25 s apart) *minus the robot's position*
    (world axes, not rotated), the velocity being the one observed at the previous step; visible
    humans (surface distance <= sensing range) first, by distance; the other rows hold 15;
    mask = 1 for visible rows. :func:`structured` gives named views.
Action
    ``Box(-v_pref, v_pref, (2,))``: world-frame velocity ``vx, vy`` (m/s), clipped to norm v_pref.
    Non-finite actions raise ``ValueError``.
Reward (CrowdNav++), on the positions before the move
    timeout 0 | human collision -20 | wall collision (Bounded) -20 | goal +10 |
    discomfort ``(dmin - 0.25) * 10 * dt`` | potential progress ``2 * (d_prev - d)``;
    plus the worst prediction penalty ``-20 / 2^(k+1)`` over visible humans' predicted positions
    within ``r + 0.3`` of the robot.
Termination
    success, human or wall collision (``terminated``); timeout at ``t >= 49 s``, the 197th step
    (``truncated``). ``info["event"]`` names the event, ``info["is_success"]`` flags success.
Starting state
    Robot start and goal ~ U(-6, 6)^2 at least 8 m apart; 20 humans on the circle of radius
    6 sqrt(2) (positive noise in [0, 2)), goals antipodal; all at rest.
Seeds
    One seed, one episode (see ``lerobot_crowdnav.sim.config.SEED_SPLITS``).

Version history: v0, first release.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, NamedTuple

import gymnasium as gym
import numpy as np
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from .config import SEED_SPLITS, CrowdSimConfig
from ..layout import ROBOT_DIM, SELF_DIM
from .engine import EVENT_NAMES, RUNNING, SUCCESS, TIMEOUT, CrowdSim

ROBOT_POLICIES = ("orca", "straight")


class StructuredObservation(NamedTuple):
    """Named views of flat observations ``(..., obs_dim)`` (no copies)."""

    robot: np.ndarray  # (..., 7) px, py, radius, gx, gy, v_pref, theta (world frame)
    robot_velocity: np.ndarray  # (..., 2) vx, vy (m/s)
    humans: np.ndarray  # (..., N, L+1, 2) positions k = 0..L relative to the robot (m)
    mask: np.ndarray  # (..., N) 1 for visible rows (sorted first), 0 for sentinel rows


def structured(obs: np.ndarray, num_humans: int = 20, prediction_steps: int = 5) -> StructuredObservation:
    obs = np.asarray(obs)
    lead = obs.shape[:-1]
    row = 2 * (prediction_steps + 1)
    h0 = SELF_DIM
    h1 = h0 + num_humans * row
    if obs.shape[-1] != h1 + num_humans:
        raise ValueError(f"observation has {obs.shape[-1]} values, expected {h1 + num_humans}")
    return StructuredObservation(
        robot=obs[..., :ROBOT_DIM],
        robot_velocity=obs[..., ROBOT_DIM:h0],
        humans=obs[..., h0:h1].reshape(*lead, num_humans, prediction_steps + 1, 2),
        mask=obs[..., h1:],
    )


def _spaces(cfg: CrowdSimConfig):
    obs_space = gym.spaces.Box(-np.inf, np.inf, (cfg.obs_dim,), np.float32)
    v = np.float32(cfg.robot_v_pref)
    act_space = gym.spaces.Box(-v, v, (2,), np.float32)
    return obs_space, act_space


def _random_train_seed(rng: np.random.Generator) -> int:
    lo, hi = SEED_SPLITS["train"]
    return int(rng.integers(lo, hi))


class CrowdNavVectorEnv(VectorEnv):
    """``num_envs`` crowd-navigation episodes stepped together, autoreset in the same step.

    Seeds: ``reset(seed=s)`` starts slot i on episode ``s + i``; ``reset(seed=[...])`` gives one
    seed per slot; later autoresets take the next seeds of the stream (``max(seeds) + 1``, ...).
    So ``reset(seed=SEED_SPLITS["test"][0])`` walks the test seeds in order.

    On the step that ends an episode, the slot is reset at once: the returned observation is the
    new episode's first one, ``info["final_obs"]`` (dense ``(B, obs_dim)``, valid where
    ``info["_final_obs"]``) holds the last observation, and ``info["final_info"]`` holds
    per-episode records for those slots: ``is_success``, ``event`` (code into ``EVENT_NAMES``),
    ``seed``, ``length`` (steps), ``return``, ``path_length`` (m), ``intrusion_steps``,
    ``intrusion_distance_sum`` (m), ``out_of_bounds`` (robot centre ever left the workspace),
    ``goal`` ``(B, 2)`` (the robot's goal, m, world frame). Every step's ``info`` carries the
    per-step quantities as arrays (see ``_step_info``).

    ``obs_mode="dict"`` returns ``{"agent_pos": obs}`` (what lerobot's ``preprocess_observation``
    reads as ``observation.state``); ``robot_policy`` may replace the actions by a built-in
    policy's (``"orca"`` or ``"straight"``), ignoring the ones passed to ``step``. With
    ``autoreset=False`` an ended slot is left as it is (and keeps stepping if asked to).
    ``freeze_ended=True`` (lerobot's env) zeroes the reward and success of a slot whose episode
    has ended, until the next ``reset``: lerobot's rollout keeps the step after an episode's end in
    its reward sums, which gymnasium's next-step autoreset makes empty and this same-step
    autoreset would make the next episode's first (-20 when it starts against a wall).
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 4, "autoreset_mode": AutoresetMode.SAME_STEP}

    def __init__(self, num_envs: int = 1, render_mode: str | None = None, obs_mode: str = "flat",
                 robot_policy: str | None = None, autoreset: bool = True, freeze_ended: bool = False,
                 config: CrowdSimConfig | None = None, **config_fields: Any):
        if config is not None and config_fields:
            raise ValueError("pass either config or config fields, not both")
        config = config or CrowdSimConfig(**config_fields)
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        if obs_mode not in ("flat", "dict"):
            raise ValueError(f"obs_mode must be 'flat' or 'dict', got {obs_mode!r}")
        if robot_policy not in (None, *ROBOT_POLICIES):
            raise ValueError(f"robot_policy must be one of {ROBOT_POLICIES} or None, got {robot_policy!r}")
        self.sim = CrowdSim(config, num_envs)
        self.config = self.sim.config
        self.num_envs = num_envs
        self.render_mode = render_mode
        self.obs_mode = obs_mode
        self.robot_policy = robot_policy
        self.autoreset = autoreset
        self.freeze_ended = freeze_ended
        self._ended = np.zeros(num_envs, np.bool_)  # since the last reset (freeze_ended)
        obs_space, act_space = _spaces(self.config)
        if obs_mode == "dict":
            obs_space = gym.spaces.Dict({"agent_pos": obs_space})
        self.single_observation_space, self.single_action_space = obs_space, act_space
        self.observation_space = batch_space(obs_space, num_envs)
        self.action_space = batch_space(act_space, num_envs)
        self._max_episode_steps = self.config.max_steps
        self.task = self.config.task
        self.task_description = f"reach the goal among {self.config.num_humans} humans"
        self._np_random = np.random.default_rng()
        self._next_seed = 0
        self._seeded = False
        self._ep_return = np.zeros(num_envs)
        self._ep_pred = np.zeros(num_envs)  # the prediction penalty's part of _ep_return
        self._ep_len = np.zeros(num_envs, np.int64)
        self._ep_path = np.zeros(num_envs)
        self._ep_intr = np.zeros(num_envs, np.int64)
        self._ep_intr_sum = np.zeros(num_envs)
        self._ep_oob = np.zeros(num_envs, np.bool_)

    # -- seeds and episodes ------------------------------------------------------------------
    def _take_seeds(self, n: int) -> np.ndarray:
        seeds = np.arange(self._next_seed, self._next_seed + n, dtype=np.int64)
        self._next_seed += n
        return seeds

    def _start(self, idx: np.ndarray, seeds: np.ndarray) -> None:
        self.sim.reset(seeds, idx)
        for k in self._ACCUMULATORS:
            getattr(self, k)[idx] = 0

    _ACCUMULATORS = ("_ep_return", "_ep_pred", "_ep_len", "_ep_path", "_ep_intr", "_ep_intr_sum", "_ep_oob")

    def state_dict(self) -> dict[str, np.ndarray]:
        """The whole batch mid-episode (simulator arrays, episode accumulators, seed stream) as
        plain arrays, e.g. for ``np.savez``; :meth:`load_state_dict` continues it exactly."""
        state = {f"sim.{k}": v for k, v in self.sim.state_dict().items()}
        state.update({k: getattr(self, k).copy() for k in self._ACCUMULATORS})
        state["_next_seed"] = np.int64(self._next_seed)
        return state

    def load_state_dict(self, state: dict[str, np.ndarray]) -> None:
        self.sim.load_state_dict({k[4:]: v for k, v in state.items() if k.startswith("sim.")})
        for k in self._ACCUMULATORS:  # a state saved before an accumulator existed: zeros
            getattr(self, k)[...] = state.get(k, 0)
        self._next_seed = int(state["_next_seed"])
        self._seeded = True

    def _obs(self, obs: np.ndarray):
        return {"agent_pos": obs} if self.obs_mode == "dict" else obs

    def reset(self, *, seed: int | list[int] | None = None, options: dict | None = None):
        if seed is None and self._seeded:
            seeds = self._take_seeds(self.num_envs)  # continue the seed stream
        elif seed is None:
            start = _random_train_seed(self._np_random)
            seeds = np.arange(start, start + self.num_envs, dtype=np.int64)
        elif isinstance(seed, (int, np.integer)):
            self._np_random = np.random.default_rng(int(seed))
            seeds = np.arange(int(seed), int(seed) + self.num_envs, dtype=np.int64)
        else:
            seeds = np.asarray(list(seed), dtype=np.int64)
            if seeds.shape != (self.num_envs,):
                raise ValueError(f"reset(seed=list) needs {self.num_envs} seeds, got {len(seeds)}")
        self._seeded = True
        self._next_seed = int(seeds.max()) + 1
        self._start(np.arange(self.num_envs), seeds)
        self._ended[:] = False
        info = {"seed": self.sim.seeds.copy()}
        return self._obs(self.sim.obs.copy()), info

    def step(self, actions):
        if self.robot_policy == "orca":
            actions = self.sim.orca_actions()
        elif self.robot_policy == "straight":
            actions = self.sim.straight_actions()
        res = self.sim.step(actions)
        reward = res.reward
        done = res.event != RUNNING
        truncated = res.event == TIMEOUT
        terminated = done & ~truncated
        self._ep_return += reward
        self._ep_pred += res.prediction_penalty
        self._ep_len += 1
        self._ep_path += res.distance
        self._ep_intr += res.intrusion
        self._ep_intr_sum += np.where(res.intrusion, res.intrusion_distance, 0.0)
        self._ep_oob |= res.out_of_bounds
        info = self._step_info(res)
        if done.any():
            idx = np.flatnonzero(done)
            info["final_obs"] = self._obs(self.sim.obs.copy())
            info["_final_obs"] = done.copy()
            info["final_info"] = {
                "is_success": res.event == SUCCESS,
                "event": res.event.copy(),
                "seed": self.sim.seeds.copy(),
                "length": self._ep_len.copy(),
                "return": self._ep_return.copy(),
                "prediction_penalty": self._ep_pred.copy(),
                "path_length": self._ep_path.copy(),
                "intrusion_steps": self._ep_intr.copy(),
                "intrusion_distance_sum": self._ep_intr_sum.copy(),
                "out_of_bounds": self._ep_oob.copy(),
                "goal": self.sim.robot_goal.copy(),
                "_is_success": done.copy(),
            }
            info["_final_info"] = done.copy()
            if self.autoreset:
                self._start(idx, self._take_seeds(len(idx)))
        if self.freeze_ended:
            frozen, self._ended = self._ended, self._ended | done
            reward = np.where(frozen, 0.0, reward)
            for part in (info, info.get("final_info", {})):
                if "is_success" in part:
                    part["is_success"] = part["is_success"] & ~frozen
        return self._obs(self.sim.obs.copy()), reward, terminated, truncated, info

    def _step_info(self, res) -> dict[str, np.ndarray]:
        """Per-step quantities (arrays of length B), for the metrics and for logging."""
        return {
            "event": res.event,
            "is_success": res.event == SUCCESS,
            "min_distance": res.min_distance,  # closest surface distance before the move (m)
            "prediction_penalty": res.prediction_penalty,  # the reward's prediction-penalty part
            "intrusion": res.intrusion,
            "intrusion_distance": res.intrusion_distance,  # closest true-future centre distance (m)
            "distance": res.distance,  # path length added this step (m)
            "out_of_bounds": res.out_of_bounds,
            "seed": self.sim.seeds.copy(),  # before any autoreset of this step
        }

    # -- built-in robot policies -------------------------------------------------------------
    def expert_actions(self, policy: str = "orca") -> np.ndarray:
        """Actions ``(B, 2)`` of a built-in robot policy for the current observations."""
        if policy == "orca":
            return self.sim.orca_actions()
        if policy == "straight":
            return self.sim.straight_actions()
        raise ValueError(f"unknown robot policy {policy!r}; choose one of {ROBOT_POLICIES}")

    # -- rendering and the Sync/AsyncVectorEnv attribute protocol ------------------------------
    def render(self):
        return self.render_slot(0) if self.render_mode == "rgb_array" else None

    def render_slot(self, b: int) -> np.ndarray:
        from .render import render_frame

        return render_frame(self.sim, b)

    def call(self, name: str, *args, **kwargs):
        """Like ``SyncVectorEnv.call``: one result per slot (lerobot's rollout uses it).

        ``call("render")`` is lazy: only the slots indexed are drawn (lerobot keeps a few)."""
        if name == "render":
            return _LazyFrames(self)
        value = getattr(self, name)
        if callable(value):
            value = value(*args, **kwargs)
        return (value,) * self.num_envs

    def get_attr(self, name: str) -> tuple:
        return (getattr(self, name),) * self.num_envs


class _LazyFrames(Sequence):
    """Frames of every slot, drawn when indexed."""

    def __init__(self, env: CrowdNavVectorEnv):
        self._env = env

    def __len__(self) -> int:
        return self._env.num_envs

    def __getitem__(self, index):
        if isinstance(index, slice):
            return [self._env.render_slot(b) for b in range(*index.indices(len(self)))]
        return self._env.render_slot(range(len(self))[index])


class CrowdNavEnv(gym.Env):
    """One crowd-navigation environment (the module docstring is its spec).

    ``info`` holds the step's ``event`` name, ``is_success``, the per-step metric quantities and,
    on the final step, the episode record (as ``CrowdNavVectorEnv``'s ``final_info``).
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 4}

    def __init__(self, render_mode: str | None = None, config: CrowdSimConfig | None = None,
                 **config_fields: Any):
        self._vec = CrowdNavVectorEnv(1, render_mode=render_mode, autoreset=False, config=config,
                                      **config_fields)
        self.config = self._vec.config
        self.render_mode = render_mode
        self.observation_space, self.action_space = _spaces(self.config)
        self._done = True

    @property
    def sim(self) -> CrowdSim:
        return self._vec.sim

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        episode_seed = _random_train_seed(self.np_random) if seed is None else seed
        obs, info = self._vec.reset(seed=int(episode_seed))
        self._done = False
        return obs[0], {"seed": int(episode_seed)}

    def step(self, action):
        if self._done:
            raise RuntimeError("the episode is over: call reset() before step()")
        action = np.asarray(action, dtype=np.float64)
        if action.shape != (2,):
            raise ValueError(f"action must have shape (2,) (vx, vy in m/s), got {action.shape}")
        obs, reward, terminated, truncated, vinfo = self._vec.step(action[None])
        info = {k: v[0].item() for k, v in vinfo.items()
                if isinstance(v, np.ndarray) and not k.startswith(("final", "_"))}
        info["event"] = EVENT_NAMES[int(vinfo["event"][0])]
        if "final_info" in vinfo:
            info["episode"] = {k: v[0].tolist() for k, v in vinfo["final_info"].items()
                               if not k.startswith("_")}
            self._done = True
        return obs[0], float(reward[0]), bool(terminated[0]), bool(truncated[0]), info

    def expert_action(self, policy: str = "orca") -> np.ndarray:
        return self._vec.expert_actions(policy)[0]

    def render(self):
        return self._vec.render()
