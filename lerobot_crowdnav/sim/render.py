"""Drawing: ``rgb_array`` frames of one environment slot, and episode videos (MP4/GIF).

Frames are drawn with Pillow (about a millisecond each, so lerobot-eval's always-on rendering
stays cheap): the workspace (solid walls in the bounded variant, a dashed outline otherwise), the
robot (green) with its goal (red cross) and velocity, the dashed sensing circle, humans as discs
of their true radius (blue when visible, grey otherwise) with the constant-velocity predicted
trajectories the robot observes.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

from .engine import CrowdSim

VIEW_HALF_SIZE = 11.0  # metres shown around the origin: humans spawn up to ~10.5 m out
ROBOT_COLOR = (40, 160, 60)
GOAL_COLOR = (220, 40, 40)
HUMAN_COLOR = (60, 110, 220)
HIDDEN_COLOR = (170, 170, 170)
WALL_COLOR = (60, 60, 60)


def render_frame(sim: CrowdSim, b: int = 0, size: int = 512) -> np.ndarray:
    """An ``(size, size, 3)`` uint8 picture of slot ``b`` in its current state."""
    cfg = sim.config
    scale = size / (2 * VIEW_HALF_SIZE)

    def px(x, y):
        return (x + VIEW_HALF_SIZE) * scale, (VIEW_HALF_SIZE - y) * scale

    def disc(x, y, r, fill, outline, width=1):
        cx, cy = px(x, y)
        draw.ellipse([cx - r * scale, cy - r * scale, cx + r * scale, cy + r * scale], fill=fill,
                     outline=outline, width=width)

    img = Image.new("RGB", (size, size), (255, 255, 255))
    draw = ImageDraw.Draw(img)
    a = cfg.arena_size
    corners = [px(-a, a), px(a, a), px(a, -a), px(-a, -a), px(-a, a)]
    if cfg.bounded:
        draw.line(corners, fill=WALL_COLOR, width=max(2, size // 128))
    else:
        for (x0, y0), (x1, y1) in zip(corners[:-1], corners[1:]):
            n = 24
            for k in range(0, n, 2):
                draw.line([(x0 + (x1 - x0) * k / n, y0 + (y1 - y0) * k / n),
                           (x0 + (x1 - x0) * (k + 1) / n, y0 + (y1 - y0) * (k + 1) / n)],
                          fill=HIDDEN_COLOR, width=1)

    rx, ry = sim.robot_pos[b]
    # Sensing circle (a human is visible when its surface is within range of the robot's).
    rs = (cfg.sensing_range + cfg.robot_radius) * scale
    cx, cy = px(rx, ry)
    for k in range(0, 72, 2):
        draw.arc([cx - rs, cy - rs, cx + rs, cy + rs], k * 5, k * 5 + 5, fill=(120, 120, 120))

    for i in range(cfg.num_humans):
        hx, hy = sim.human_pos[b, i]
        if sim.visible[b, i]:
            traj = [px(*p) for p in sim.pred[b, i]]
            draw.line(traj, fill=HUMAN_COLOR, width=1)
            for q in traj[1:]:
                draw.ellipse([q[0] - 1.5, q[1] - 1.5, q[0] + 1.5, q[1] + 1.5], fill=HUMAN_COLOR)
            disc(hx, hy, sim.human_radius[b, i], (170, 195, 245), HUMAN_COLOR, 2)
        else:
            disc(hx, hy, sim.human_radius[b, i], (230, 230, 230), HIDDEN_COLOR, 1)

    gx, gy = px(*sim.robot_goal[b])
    g = 0.3 * scale
    draw.line([gx - g, gy - g, gx + g, gy + g], fill=GOAL_COLOR, width=3)
    draw.line([gx - g, gy + g, gx + g, gy - g], fill=GOAL_COLOR, width=3)
    disc(rx, ry, cfg.robot_radius, ROBOT_COLOR, (20, 90, 30), 2)
    vx, vy = sim.robot_vel[b]
    draw.line([px(rx, ry), px(rx + vx, ry + vy)], fill=(20, 90, 30), width=2)

    t = sim.step_count[b] * cfg.dt
    draw.text((6, 6), f"{cfg.task}  seed {sim.seeds[b]}  t = {t:5.2f} s", fill=(0, 0, 0))
    return np.asarray(img)


def _shared_palette(frames: list[np.ndarray]) -> list[Image.Image] | None:
    """The frames as palette images sharing one exact palette, their own colours, or None when they
    hold more than 256. Drawn frames hold about two hundred (flat fills, anti-aliased text), and
    indexing them costs a fraction of Pillow's per-frame quantization and palette optimization
    (several times the drawing itself); the GIF stays lossless, a little larger."""
    keys = [(f[..., 0].astype(np.uint32) << 16) | (f[..., 1].astype(np.uint32) << 8) | f[..., 2] for f in frames]
    index = np.zeros(1 << 24, np.uint8)  # first a mark per colour present, then its palette slot
    for k in keys:
        index[k] = 1
    colours = np.flatnonzero(index)
    if len(colours) > 256:
        return None
    index[colours] = np.arange(len(colours))
    palette = np.stack([colours >> 16, (colours >> 8) & 255, colours & 255], axis=1).astype(np.uint8).tobytes()
    images = []
    for k in keys:
        im = Image.fromarray(index[k])  # "L", made "P" by its palette
        im.putpalette(palette)
        images.append(im)
    return images


def save_video(frames: list[np.ndarray], path: str | Path, fps: float = 4.0) -> Path:
    """Write frames to ``.gif`` (Pillow) or ``.mp4`` (H.264 through PyAV, which ships FFmpeg)."""
    path = Path(path)
    if not frames:
        raise ValueError("no frames to write")
    path.parent.mkdir(parents=True, exist_ok=True)
    suffix = path.suffix.lower()
    if suffix == ".gif":
        images = _shared_palette(frames)
        if images is None:  # more colours than a GIF palette: Pillow quantizes each frame
            images = [Image.fromarray(f) for f in frames]
        images[0].save(path, save_all=True, append_images=images[1:], duration=int(round(1000 / fps)), loop=0,
                       optimize=False)
    elif suffix == ".mp4":
        import av

        with av.open(str(path), mode="w") as container:
            stream = container.add_stream("libx264", rate=int(round(fps)))
            h, w = frames[0].shape[:2]
            stream.width, stream.height = w - w % 2, h - h % 2
            stream.pix_fmt = "yuv420p"
            for f in frames:
                frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(f[: stream.height, : stream.width]),
                                                   format="rgb24")
                container.mux(stream.encode(frame))
            container.mux(stream.encode())
    else:
        raise ValueError(f"unsupported video format {suffix!r}: use .mp4 or .gif")
    return path


def record_episode(env, path: str | Path, seed: int, policy: str = "orca",
                   max_steps: int | None = None) -> Path:
    """Run one episode of a single ``CrowdNavEnv`` with a built-in robot policy and save it.

    ``policy`` is ``"orca"``, ``"straight"`` or a callable ``obs -> action``.
    """
    obs, _ = env.reset(seed=seed)
    frames = [render_frame(env.sim, 0)]
    limit = max_steps or env.config.max_steps
    for _ in range(limit):
        action = policy(obs) if callable(policy) else env.expert_action(policy)
        obs, _, terminated, truncated, _ = env.step(action)
        frames.append(render_frame(env.sim, 0))
        if terminated or truncated:
            break
    return save_video(frames, path, fps=env.metadata["render_fps"])
