"""The crowd observation layout: the one definition the simulator, the policies and the
processors read (``observation.state``, float32, robot-centred where noted).

    [ robot 7 | robot velocity 2 | humans N x 2(L+1) | mask N ]      N = 20, L = 5: 269 floats

* robot (world frame): px, py (m), radius (m), gx, gy (m), v_pref (m/s), theta (rad)
* robot velocity (world frame): vx, vy (m/s)
* humans: one row per human slot, the positions at k = 0..L prediction steps relative to the
  robot (m), visible humans first (nearest first); rows of invisible slots hold ``SENTINEL``
* mask: 1 for the visible rows, 0 for the sentinel rows

It imports nothing but ``typing`` at run time, so the policy plugins can read it without loading the
simulator.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:  # annotations only
    from torch import Tensor

ROBOT_DIM = 7  # px, py, radius, gx, gy, v_pref, theta
VELOCITY_DIM = 2  # vx, vy
SELF_DIM = ROBOT_DIM + VELOCITY_DIM  # the robot's own floats (the paper's w): 9
# The value of every float of an invisible human's row: the simulator's default (--env.sentinel),
# and what PDPO's state statistics leave out (its config's sentinel_value).
SENTINEL = 15.0


def human_row_dim(prediction_steps: int) -> int:
    """Floats of one human row: x, y at k = 0..L."""
    return 2 * (prediction_steps + 1)


def humans_slice(num_humans: int, prediction_steps: int) -> slice:
    return slice(SELF_DIM, SELF_DIM + num_humans * human_row_dim(prediction_steps))


def mask_slice(num_humans: int, prediction_steps: int) -> slice:
    start = humans_slice(num_humans, prediction_steps).stop
    return slice(start, start + num_humans)


def obs_dim(num_humans: int, prediction_steps: int) -> int:
    return mask_slice(num_humans, prediction_steps).stop


def visible_prefix_groups(count: Tensor, groups: int) -> tuple[list[tuple[Tensor, int]], Tensor]:
    """Batch rows in ``groups`` groups of similar visible counts, for a network that needs only
    each row's visible human rows, which come first: ``count (B,)`` (long tensor) -> the groups
    as (row indices, width k >= 1: the group's largest count, the slots to keep), and the
    permutation that puts the groups' concatenated outputs back in batch order. Sorting by count
    keeps each group's padding small; a few groups keep the per-group overhead small."""
    order = count.argsort()
    return [(rows, max(int(count[rows[-1]]), 1)) for rows in order.chunk(min(groups, len(order)))], order.argsort()


def check_sentinel(policy_config, sentinel: float) -> None:
    """A policy that knows the sentinel (``sentinel_value``: PDPO normalizes the human rows with
    statistics that leave the sentinel rows out) must read an env that writes the same one."""
    expected = getattr(policy_config, "sentinel_value", sentinel)
    if expected != sentinel:
        raise ValueError(f"the policy was trained on invisible-human rows of {expected} (its sentinel_value); the env "
                         f"writes {sentinel} (--env.sentinel): its normalization would be wrong")


def check_policy_features(config, policy: str) -> None:
    """A lerobot policy config reading this layout must have the state input of its size
    (``config.num_humans``, ``config.prediction_steps``) and a 2-D velocity action."""
    from lerobot.configs.types import FeatureType
    from lerobot.utils.constants import ACTION, OBS_STATE

    state = config.input_features.get(OBS_STATE)
    if state is None or state.type is not FeatureType.STATE:
        raise ValueError(f"{policy} needs the state input {OBS_STATE!r}, got {list(config.input_features)}")
    size = obs_dim(config.num_humans, config.prediction_steps)
    if tuple(state.shape) != (size,):
        raise ValueError(f"{OBS_STATE} has shape {tuple(state.shape)}, but num_humans={config.num_humans} and "
                         f"prediction_steps={config.prediction_steps} need ({size},)")
    action = config.output_features.get(ACTION)
    if action is None or tuple(action.shape) != (2,):
        raise ValueError(f"{policy} outputs 2-D velocities as {ACTION!r}, got {config.output_features}")
