"""ORCA (optimal reciprocal collision avoidance), RVO2 semantics, compiled with numba.

The functions mirror RVO2's ``Agent::computeNewVelocity`` one to one so that a reader can hold
them next to the paper (van den Berg et al., 2011) and the C++ library:

- :func:`obstacle_orca_lines`  — static-obstacle half-planes (full responsibility),
- :func:`agent_orca_lines`     — agent-agent half-planes (half responsibility, collision case
  projected on the cut-off circle of one time step),
- :func:`linear_program1/2/3` — incremental 2-D LP on the max-speed disc, with the infeasible
  fallback (LP3) that minimises the largest violation while keeping obstacle lines hard.

Units: metres, seconds, m/s, world frame. A set of half-planes is an ``(M, 4)`` float64 array of
rows ``(point_x, point_y, direction_x, direction_y)``; the permitted side is the left of the
direction. Everything is float64 (RVO2 uses float32; the geometry is the same).

Obstacles are polygons stored flat (see :func:`make_obstacles`): ``points (K, 2)``,
``unit_dir (K, 2)``, ``next_idx (K,)``, ``prev_idx (K,)``, ``convex (K,)``. Vertices of an
obstacle are listed counter-clockwise; a bounding box that keeps agents *inside* is listed
clockwise (RVO2's convention).
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

RVO_EPSILON = 1e-5  # RVO2's Definitions.h

_jit = nb.njit(cache=True, inline="always", error_model="numpy")


@_jit
def det(ax, ay, bx, by):
    return ax * by - ay * bx


@_jit
def linear_program1(lines, line_no, radius, opt_x, opt_y, direction_opt):
    """Best point on line ``line_no`` within the disc and lines ``0..line_no-1``.

    Returns ``(feasible, x, y)``.
    """
    px, py, dx, dy = lines[line_no, 0], lines[line_no, 1], lines[line_no, 2], lines[line_no, 3]
    dot = px * dx + py * dy
    discriminant = dot * dot + radius * radius - (px * px + py * py)
    if discriminant < 0.0:
        return False, 0.0, 0.0  # the max-speed disc misses the line entirely
    sqrt_disc = math.sqrt(discriminant)
    t_left = -dot - sqrt_disc
    t_right = -dot + sqrt_disc
    for i in range(line_no):
        denominator = det(dx, dy, lines[i, 2], lines[i, 3])
        numerator = det(lines[i, 2], lines[i, 3], px - lines[i, 0], py - lines[i, 1])
        if math.fabs(denominator) <= RVO_EPSILON:
            if numerator < 0.0:
                return False, 0.0, 0.0  # (almost) parallel and pointing away
            continue
        t = numerator / denominator
        if denominator >= 0.0:
            t_right = min(t_right, t)  # line i bounds line_no on the right
        else:
            t_left = max(t_left, t)  # line i bounds line_no on the left
        if t_left > t_right:
            return False, 0.0, 0.0
    if direction_opt:
        if opt_x * dx + opt_y * dy > 0.0:
            return True, px + t_right * dx, py + t_right * dy
        return True, px + t_left * dx, py + t_left * dy
    t = dx * (opt_x - px) + dy * (opt_y - py)
    if t < t_left:
        t = t_left
    elif t > t_right:
        t = t_right
    return True, px + t * dx, py + t * dy


@_jit
def linear_program2(lines, n_lines, radius, opt_x, opt_y, direction_opt):
    """Point of the disc closest to ``opt`` (or furthest along it) satisfying all lines.

    Returns ``(fail_line, x, y)``; ``fail_line == n_lines`` means success, otherwise the index of
    the first line that made the program infeasible (result = best point before it).
    """
    if direction_opt:
        rx, ry = opt_x * radius, opt_y * radius
    elif opt_x * opt_x + opt_y * opt_y > radius * radius:
        norm = math.sqrt(opt_x * opt_x + opt_y * opt_y)
        rx, ry = opt_x / norm * radius, opt_y / norm * radius
    else:
        rx, ry = opt_x, opt_y
    for i in range(n_lines):
        if det(lines[i, 2], lines[i, 3], lines[i, 0] - rx, lines[i, 1] - ry) > 0.0:
            ok, nx, ny = linear_program1(lines, i, radius, opt_x, opt_y, direction_opt)
            if not ok:
                return i, rx, ry
            rx, ry = nx, ny
    return n_lines, rx, ry


@_jit
def linear_program3(lines, n_lines, num_obst_lines, begin_line, radius, rx, ry, proj):
    """Infeasible case: minimise the maximum violation of the agent lines (obstacle lines hard).

    ``proj`` is scratch space of at least ``n_lines`` rows. Returns the new ``(x, y)``.
    """
    distance = 0.0
    for i in range(begin_line, n_lines):
        ix, iy, idx_, idy = lines[i, 0], lines[i, 1], lines[i, 2], lines[i, 3]
        if det(idx_, idy, ix - rx, iy - ry) > distance:
            n_proj = num_obst_lines
            proj[:num_obst_lines, :] = lines[:num_obst_lines, :]
            for j in range(num_obst_lines, i):
                jx, jy, jdx, jdy = lines[j, 0], lines[j, 1], lines[j, 2], lines[j, 3]
                determinant = det(idx_, idy, jdx, jdy)
                if math.fabs(determinant) <= RVO_EPSILON:
                    if idx_ * jdx + idy * jdy > 0.0:
                        continue  # parallel, same direction
                    qx, qy = 0.5 * (ix + jx), 0.5 * (iy + jy)
                else:
                    s = det(jdx, jdy, ix - jx, iy - jy) / determinant
                    qx, qy = ix + s * idx_, iy + s * idy
                ddx, ddy = jdx - idx_, jdy - idy
                dnorm = math.sqrt(ddx * ddx + ddy * ddy)
                proj[n_proj, 0] = qx
                proj[n_proj, 1] = qy
                proj[n_proj, 2] = ddx / dnorm
                proj[n_proj, 3] = ddy / dnorm
                n_proj += 1
            fail, nx, ny = linear_program2(proj, n_proj, radius, -idy, idx_, True)
            if fail >= n_proj:
                rx, ry = nx, ny
            # else: floating-point failure; RVO2 keeps the previous result
            distance = det(idx_, idy, ix - rx, iy - ry)
    return rx, ry


@_jit
def agent_orca_line(px, py, vx, vy, radius, ox, oy, ovx, ovy, oradius, inv_time_horizon,
                    inv_time_step):
    """ORCA half-plane induced on the agent at ``p`` by neighbour ``o`` (half responsibility).

    Returns ``(point_x, point_y, dir_x, dir_y)``.
    """
    rel_px, rel_py = ox - px, oy - py
    rel_vx, rel_vy = vx - ovx, vy - ovy
    dist_sq = rel_px * rel_px + rel_py * rel_py
    combined_radius = radius + oradius
    combined_radius_sq = combined_radius * combined_radius
    if dist_sq > combined_radius_sq:
        # No collision: w = vector from cut-off centre to relative velocity.
        wx = rel_vx - inv_time_horizon * rel_px
        wy = rel_vy - inv_time_horizon * rel_py
        w_length_sq = wx * wx + wy * wy
        dot1 = wx * rel_px + wy * rel_py
        if dot1 < 0.0 and dot1 * dot1 > combined_radius_sq * w_length_sq:
            # Project on the cut-off circle.
            w_length = math.sqrt(w_length_sq)
            ux_, uy_ = wx / w_length, wy / w_length
            dx, dy = uy_, -ux_
            scale = combined_radius * inv_time_horizon - w_length
            ux, uy = scale * ux_, scale * uy_
        else:
            # Project on the legs.
            leg = math.sqrt(dist_sq - combined_radius_sq)
            if det(rel_px, rel_py, wx, wy) > 0.0:
                dx = (rel_px * leg - rel_py * combined_radius) / dist_sq
                dy = (rel_px * combined_radius + rel_py * leg) / dist_sq
            else:
                dx = -(rel_px * leg + rel_py * combined_radius) / dist_sq
                dy = -(-rel_px * combined_radius + rel_py * leg) / dist_sq
            dot2 = rel_vx * dx + rel_vy * dy
            ux, uy = dot2 * dx - rel_vx, dot2 * dy - rel_vy
    else:
        # Collision: project on the cut-off circle of time step dt.
        wx = rel_vx - inv_time_step * rel_px
        wy = rel_vy - inv_time_step * rel_py
        w_length = math.sqrt(wx * wx + wy * wy)
        if w_length > 1e-12:
            ux_, uy_ = wx / w_length, wy / w_length
        else:
            # Coincident agents with equal velocities: RVO2 divides by zero (NaN); push along +x.
            w_length, ux_, uy_ = 0.0, 1.0, 0.0
        dx, dy = uy_, -ux_
        scale = combined_radius * inv_time_step - w_length
        ux, uy = scale * ux_, scale * uy_
    return vx + 0.5 * ux, vy + 0.5 * uy, dx, dy


@_jit
def insert_sorted(keys, values, slot, key, value):
    """Insertion step of RVO2's neighbour lists: put ``(key, value)`` into the ascending
    ``keys[:slot + 1]`` by shifting larger keys up from ``slot`` (stable for equal keys)."""
    k = slot
    while k > 0 and key < keys[k - 1]:
        keys[k] = keys[k - 1]
        values[k] = values[k - 1]
        k -= 1
    keys[k] = key
    values[k] = value


@_jit
def _push_line(lines, n, px, py, dx, dy):
    lines[n, 0] = px
    lines[n, 1] = py
    lines[n, 2] = dx
    lines[n, 3] = dy
    return n + 1


@_jit
def _normalized(x, y):
    n = math.sqrt(x * x + y * y)
    return x / n, y / n


@_jit
def _tangent_legs(rx, ry, dist_sq, radius):
    """Left and right leg directions (unit) from the agent, tangent to the disc of ``radius``
    around the relative position ``(rx, ry)`` at squared distance ``dist_sq``."""
    leg = math.sqrt(dist_sq - radius * radius)
    return ((rx * leg - ry * radius) / dist_sq, (rx * radius + ry * leg) / dist_sq,
            (rx * leg + ry * radius) / dist_sq, (-rx * radius + ry * leg) / dist_sq)


@_jit
def obstacle_orca_lines(px, py, vx, vy, radius, time_horizon_obst, max_speed, obst_points,
                        obst_unit_dir, obst_next, obst_prev, obst_convex, lines, order, dist):
    """Write the obstacle ORCA lines of an agent into ``lines``; return their count.

    Obstacle neighbours are the edges the agent sees from their right side within
    ``time_horizon_obst * max_speed + radius`` (RVO2's kd-tree query), processed by increasing
    distance. ``order``/``dist`` are scratch arrays of length K.
    """
    n_edges = obst_points.shape[0]
    range_sq = (time_horizon_obst * max_speed + radius) ** 2
    # Obstacle neighbours, insertion-sorted by squared distance (Agent::insertObstacleNeighbor).
    n_nb = 0
    for e in range(n_edges):
        nx_ = obst_next[e]
        ax, ay = obst_points[e, 0], obst_points[e, 1]
        bx, by = obst_points[nx_, 0], obst_points[nx_, 1]
        left_of = det(ax - px, ay - py, bx - ax, by - ay)  # leftOf(a, b, p)
        if left_of >= 0.0:
            continue  # agent not on the right side: cannot see this edge
        ex, ey = bx - ax, by - ay
        r = ((px - ax) * ex + (py - ay) * ey) / (ex * ex + ey * ey)
        if r < 0.0:
            d_sq = (px - ax) ** 2 + (py - ay) ** 2
        elif r > 1.0:
            d_sq = (px - bx) ** 2 + (py - by) ** 2
        else:
            d_sq = (px - ax - r * ex) ** 2 + (py - ay - r * ey) ** 2
        if d_sq >= range_sq:
            continue
        insert_sorted(dist, order, n_nb, d_sq, e)
        n_nb += 1

    inv_th = 1.0 / time_horizon_obst
    radius_sq = radius * radius
    n = 0
    for q in range(n_nb):
        o1 = order[q]
        o2 = obst_next[o1]
        rp1x, rp1y = obst_points[o1, 0] - px, obst_points[o1, 1] - py
        rp2x, rp2y = obst_points[o2, 0] - px, obst_points[o2, 1] - py

        # Already covered by previously constructed obstacle lines?
        covered = False
        for j in range(n):
            if (det(inv_th * rp1x - lines[j, 0], inv_th * rp1y - lines[j, 1], lines[j, 2],
                    lines[j, 3]) - inv_th * radius >= -RVO_EPSILON
                    and det(inv_th * rp2x - lines[j, 0], inv_th * rp2y - lines[j, 1], lines[j, 2],
                            lines[j, 3]) - inv_th * radius >= -RVO_EPSILON):
                covered = True
                break
        if covered:
            continue

        dist_sq1 = rp1x * rp1x + rp1y * rp1y
        dist_sq2 = rp2x * rp2x + rp2y * rp2y
        ovx, ovy = obst_points[o2, 0] - obst_points[o1, 0], obst_points[o2, 1] - obst_points[o1, 1]
        s = (-rp1x * ovx - rp1y * ovy) / (ovx * ovx + ovy * ovy)
        dist_sq_line = (-rp1x - s * ovx) ** 2 + (-rp1y - s * ovy) ** 2

        if s < 0.0 and dist_sq1 <= radius_sq:
            # Collision with the left vertex; ignore if non-convex.
            if obst_convex[o1]:
                dx, dy = _normalized(-rp1y, rp1x)
                n = _push_line(lines, n, 0.0, 0.0, dx, dy)
            continue
        elif s > 1.0 and dist_sq2 <= radius_sq:
            # Collision with the right vertex; ignore if non-convex or handled by the next edge.
            if obst_convex[o2] and det(rp2x, rp2y, obst_unit_dir[o2, 0], obst_unit_dir[o2, 1]) >= 0.0:
                dx, dy = _normalized(-rp2y, rp2x)
                n = _push_line(lines, n, 0.0, 0.0, dx, dy)
            continue
        elif s >= 0.0 and s <= 1.0 and dist_sq_line <= radius_sq:
            # Collision with the segment.
            n = _push_line(lines, n, 0.0, 0.0, -obst_unit_dir[o1, 0], -obst_unit_dir[o1, 1])
            continue

        # No collision: legs (both may come from one vertex when viewed obliquely).
        if s < 0.0 and dist_sq_line <= radius_sq:
            if not obst_convex[o1]:
                continue
            o2 = o1
            llx, lly, rlx, rly = _tangent_legs(rp1x, rp1y, dist_sq1, radius)
        elif s > 1.0 and dist_sq_line <= radius_sq:
            if not obst_convex[o2]:
                continue
            o1 = o2
            llx, lly, rlx, rly = _tangent_legs(rp2x, rp2y, dist_sq2, radius)
        else:
            if obst_convex[o1]:
                llx, lly, _, _ = _tangent_legs(rp1x, rp1y, dist_sq1, radius)
            else:
                llx, lly = -obst_unit_dir[o1, 0], -obst_unit_dir[o1, 1]
            if obst_convex[o2]:
                _, _, rlx, rly = _tangent_legs(rp2x, rp2y, dist_sq2, radius)
            else:
                rlx, rly = obst_unit_dir[o1, 0], obst_unit_dir[o1, 1]

        # A leg of a convex vertex never points into the neighbouring edge: use that edge instead,
        # and add no constraint if the velocity projects on such a "foreign" leg.
        left_nb = obst_prev[o1]
        left_foreign = False
        right_foreign = False
        if obst_convex[o1] and det(llx, lly, -obst_unit_dir[left_nb, 0], -obst_unit_dir[left_nb, 1]) >= 0.0:
            llx, lly = -obst_unit_dir[left_nb, 0], -obst_unit_dir[left_nb, 1]
            left_foreign = True
        if obst_convex[o2] and det(rlx, rly, obst_unit_dir[o2, 0], obst_unit_dir[o2, 1]) <= 0.0:
            rlx, rly = obst_unit_dir[o2, 0], obst_unit_dir[o2, 1]
            right_foreign = True

        lcx, lcy = inv_th * (obst_points[o1, 0] - px), inv_th * (obst_points[o1, 1] - py)
        rcx, rcy = inv_th * (obst_points[o2, 0] - px), inv_th * (obst_points[o2, 1] - py)
        cvx, cvy = rcx - lcx, rcy - lcy
        same = o1 == o2
        t = 0.5 if same else ((vx - lcx) * cvx + (vy - lcy) * cvy) / (cvx * cvx + cvy * cvy)
        t_left = (vx - lcx) * llx + (vy - lcy) * lly
        t_right = (vx - rcx) * rlx + (vy - rcy) * rly

        if (t < 0.0 and t_left < 0.0) or (same and t_left < 0.0 and t_right < 0.0):
            # Project on the left cut-off circle.
            wx, wy = _normalized(vx - lcx, vy - lcy)
            n = _push_line(lines, n, lcx + radius * inv_th * wx, lcy + radius * inv_th * wy, wy, -wx)
            continue
        elif t > 1.0 and t_right < 0.0:
            # Project on the right cut-off circle.
            wx, wy = _normalized(vx - rcx, vy - rcy)
            n = _push_line(lines, n, rcx + radius * inv_th * wx, rcy + radius * inv_th * wy, wy, -wx)
            continue

        # Project on the left leg, the right leg or the cut-off line, whichever is closest.
        if t < 0.0 or t > 1.0 or same:
            d_cut = math.inf
        else:
            d_cut = (vx - (lcx + t * cvx)) ** 2 + (vy - (lcy + t * cvy)) ** 2
        d_left = math.inf if t_left < 0.0 else (vx - (lcx + t_left * llx)) ** 2 + (vy - (lcy + t_left * lly)) ** 2
        d_right = math.inf if t_right < 0.0 else (vx - (rcx + t_right * rlx)) ** 2 + (vy - (rcy + t_right * rly)) ** 2

        if d_cut <= d_left and d_cut <= d_right:
            dx, dy = -obst_unit_dir[o1, 0], -obst_unit_dir[o1, 1]
            n = _push_line(lines, n, lcx + radius * inv_th * (-dy), lcy + radius * inv_th * dx, dx, dy)
        elif d_left <= d_right:
            if left_foreign:
                continue
            n = _push_line(lines, n, lcx + radius * inv_th * (-lly), lcy + radius * inv_th * llx, llx, lly)
        else:
            if right_foreign:
                continue
            dx, dy = -rlx, -rly
            n = _push_line(lines, n, rcx + radius * inv_th * (-dy), rcy + radius * inv_th * dx, dx, dy)
    return n


@nb.njit(cache=True, error_model="numpy")
def compute_new_velocity(ego, positions, velocities, radii, candidates, n_candidates, max_speed,
                         pref_x, pref_y, neighbor_dist, max_neighbors, time_horizon,
                         time_horizon_obst, time_step, obst_points, obst_unit_dir, obst_next,
                         obst_prev, obst_convex, lines, proj, nb_idx, nb_dist, ob_idx, ob_dist):
    """RVO2 ``Agent::computeNeighbors`` + ``computeNewVelocity`` for agent ``ego``.

    ``positions``/``velocities`` ``(A, 2)`` and ``radii`` ``(A,)`` hold every agent of the scene
    (radii already include any safety margin); ``candidates[:n_candidates]`` are the agent indices
    the ego may consider as neighbours (it is skipped if listed). Obstacle arrays may be empty.
    ``lines``/``proj`` ``(>= K + A, 4)``, ``nb_idx``/``nb_dist`` ``(>= A)`` and ``ob_idx``/``ob_dist``
    ``(>= K)`` are scratch. Returns the new velocity ``(vx, vy)``.
    """
    px, py = positions[ego, 0], positions[ego, 1]
    vx, vy = velocities[ego, 0], velocities[ego, 1]
    radius = radii[ego]

    n_obst = obstacle_orca_lines(px, py, vx, vy, radius, time_horizon_obst, max_speed, obst_points,
                                 obst_unit_dir, obst_next, obst_prev, obst_convex, lines, ob_idx,
                                 ob_dist)

    # Agent neighbours within neighbor_dist, the max_neighbors closest, sorted by distance
    # (Agent::insertAgentNeighbor, including its shrinking of the range once full).
    range_sq = neighbor_dist * neighbor_dist
    n_nb = 0
    for c in range(n_candidates):
        j = candidates[c]
        if j == ego:
            continue
        d_sq = (px - positions[j, 0]) ** 2 + (py - positions[j, 1]) ** 2
        if d_sq < range_sq:
            if n_nb < max_neighbors:
                n_nb += 1
            insert_sorted(nb_dist, nb_idx, n_nb - 1, d_sq, j)  # when full, the farthest goes
            if n_nb == max_neighbors:
                range_sq = nb_dist[n_nb - 1]

    inv_th = 1.0 / time_horizon
    inv_dt = 1.0 / time_step
    n = n_obst
    for q in range(n_nb):
        j = nb_idx[q]
        lpx, lpy, ldx, ldy = agent_orca_line(px, py, vx, vy, radius, positions[j, 0], positions[j, 1],
                                             velocities[j, 0], velocities[j, 1], radii[j], inv_th,
                                             inv_dt)
        n = _push_line(lines, n, lpx, lpy, ldx, ldy)

    fail, rx, ry = linear_program2(lines, n, max_speed, pref_x, pref_y, False)
    if fail < n:
        rx, ry = linear_program3(lines, n, n_obst, fail, max_speed, rx, ry, proj)
    # RVO2 returns the LP point as is; in degenerate scenes (coincident agents, lines parallel
    # within RVO_EPSILON) rounding can leave it ~1e-6 outside the max-speed disc. Keep the bound.
    speed = math.sqrt(rx * rx + ry * ry)
    if speed > max_speed:
        rx, ry = rx * (max_speed / speed), ry * (max_speed / speed)
    return rx, ry


def make_obstacles(polygons: list[np.ndarray]):
    """Flatten polygons (each ``(V, 2)``, RVO2 vertex order) into the kernel's obstacle arrays.

    Mirrors ``RVOSimulator::addObstacle``: a 2-vertex obstacle is a convex segment; otherwise a
    vertex is convex when the polygon turns left there (``leftOf(prev, v, next) >= 0``).
    """
    points, unit_dir, next_idx, prev_idx, convex = [], [], [], [], []
    for poly in polygons:
        poly = np.asarray(poly, dtype=np.float64)
        v = len(poly)
        if v < 2:
            raise ValueError("an obstacle needs at least two vertices")
        base = len(points)
        for i in range(v):
            prev_p, p, next_p = poly[i - 1], poly[i], poly[(i + 1) % v]
            points.append(p)
            prev_idx.append(base + (i - 1) % v)
            next_idx.append(base + (i + 1) % v)
            d = next_p - p
            unit_dir.append(d / np.linalg.norm(d))
            if v == 2:
                convex.append(True)
            else:
                left_of = (p[0] - prev_p[0]) * (next_p[1] - prev_p[1]) - (p[1] - prev_p[1]) * (next_p[0] - prev_p[0])
                convex.append(left_of >= 0.0)
    if not points:
        return (np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0, np.int64), np.zeros(0, np.int64),
                np.zeros(0, np.bool_))
    return (np.array(points), np.array(unit_dir), np.array(next_idx, np.int64),
            np.array(prev_idx, np.int64), np.array(convex, np.bool_))


def bounding_box(half_size: float) -> np.ndarray:
    """The square ``[-h, h]^2`` as an RVO2 boundary: vertices clockwise, agents kept inside."""
    h = half_size
    return np.array([[-h, h], [h, h], [h, -h], [-h, -h]], dtype=np.float64)
