"""The crowd observation layout: the one definition the simulator, the policies and the
processors read (``observation.state``, float32, robot-centred where noted).

    [ robot 7 | robot velocity 2 | humans N x 2(L+1) | mask N ]      N = 20, L = 5: 269 floats

* robot (world frame): px, py (m), radius (m), gx, gy (m), v_pref (m/s), theta (rad)
* robot velocity (world frame): vx, vy (m/s)
* humans: one row per human slot, the positions at k = 0..L prediction steps relative to the
  robot (m), visible humans first (nearest first); rows of invisible slots hold the sentinel 15
* mask: 1 for the visible rows, 0 for the sentinel rows

The module imports nothing, so the policy plugin can read it without loading the simulator.
"""

from __future__ import annotations

ROBOT_DIM = 7  # px, py, radius, gx, gy, v_pref, theta
VELOCITY_DIM = 2  # vx, vy
SELF_DIM = ROBOT_DIM + VELOCITY_DIM  # the robot's own floats (the paper's w): 9


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
