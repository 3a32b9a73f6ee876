"""The figures: the fine-tuning curves' panels; the action-chunk figures, drawing functions on
hand-made scenes (size, content, colours), and ``lerobot_crowdnav.evaluation.figures``
(record_snapshots and the CLI) end to end on a tiny PDPO checkpoint."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from conftest import make_tiny_checkpoint
from PIL import Image

from lerobot_crowdnav.evaluation import figures
from lerobot_crowdnav.measure.plots import chunk_positions, plot_finetune_curves, plot_multimodality, plot_storyboard
from lerobot_crowdnav.sim.config import CrowdSimConfig
from lerobot_crowdnav.sim.envs import CrowdNavEnv, structured

SENSING, DT = 6.0, 0.25
# Pixel sizes: panels of 3.2 x 3.4 in, a 0.6 in legend band, 0.3 in for a title, at 150 dpi.
PANEL_W, PANEL_H, LEGEND_H, TITLE_H = 480, 510, 90, 45


def make_obs(robot=(1.0, -2.0), goal=(3.0, 0.0), humans=(), hidden=()) -> np.ndarray:
    """An observation with visible humans ``((pos, vel), ...)`` relative to the robot, and rows
    ``hidden`` with in-range coordinates but mask 0 (which must not be drawn)."""
    obs = np.full(269, 15.0, np.float32)
    obs[:7] = [*robot, 0.2, *goal, 1.0, np.pi / 2]
    obs[7:9] = [0.6, 0.8]
    obs[-20:] = 0.0
    rows = [(p, v, 1.0) for p, v in humans] + [(p, v, 0.0) for p, v in hidden]
    for i, (p, v, m) in enumerate(rows):
        obs[9 + 12 * i: 9 + 12 * (i + 1)] = np.array([np.add(p, np.multiply(v, DT * k)) for k in range(6)]).ravel()
        obs[-20 + i] = m
    return obs


CROWD = (((2.0, 1.0), (0.5, -0.4)), ((-3.0, 2.5), (0.0, 1.0)), ((0.5, -4.0), (-1.0, 0.0)))
CHUNK = np.array([[0.8, 0.6]] * 5)


def colour_counts(img: np.ndarray) -> dict[str, int]:
    r, g, b = (img[..., i].astype(int) for i in range(3))
    return {
        "red": int(((r > 180) & (g < 80) & (b < 80)).sum()),  # chunk-end crosses
        "blue": int(((b > 180) & (r < 100) & (g < 140)).sum()),  # humans
        "green": int(((g > 130) & (r < 90) & (b < 100)).sum()),  # robot
        "orange": int(((r > 200) & (g > 120) & (g < 190) & (b < 60)).sum()),  # goal
    }


def panels(path: Path, n: int) -> list[np.ndarray]:
    """The pixels of each panel of a figure of ``n`` panels (rows of 5), legend band excluded."""
    img = np.asarray(Image.open(path).convert("RGB"))
    top = img.shape[0] - LEGEND_H - ((-(-n // 5)) * PANEL_H)
    return [img[top + (i // 5) * PANEL_H: top + (i // 5 + 1) * PANEL_H, (i % 5) * PANEL_W: (i % 5 + 1) * PANEL_W]
            for i in range(n)]


def test_chunk_positions_integrate_velocities_over_dt():
    p = chunk_positions(np.array([[1.0, 0.0]] * 5), DT)
    np.testing.assert_allclose(p[0], [0, 0])
    np.testing.assert_allclose(p[-1], [1.25, 0.0])  # 1 m/s for 5 x 0.25 s
    many = chunk_positions(np.stack([CHUNK, -CHUNK]), DT)
    assert many.shape == (2, 6, 2)
    np.testing.assert_allclose(many[1, -1], [-1.0, -0.75])


def test_storyboard_png_size_and_content(tmp_path):
    snaps = [
        {"obs": make_obs(humans=CROWD), "chunk": CHUNK, "t": 0.0},
        {"obs": make_obs(hidden=[((2.0, 2.0), (0.0, 0.0))]), "chunk": CHUNK * 0.5, "t": 1.0},  # no visible human
        {"obs": make_obs(goal=(-8.0, 9.0), humans=CROWD[:1]), "chunk": -CHUNK, "t": 2.25},  # goal off the panel
    ]
    path = plot_storyboard(snaps, tmp_path / "sub" / "story.png", SENSING, DT, title="hand-made", arena_size=6.0)
    assert path == tmp_path / "sub" / "story.png"
    img = Image.open(path)
    assert img.size == (3 * PANEL_W, PANEL_H + LEGEND_H + TITLE_H)
    rgb = np.asarray(img.convert("RGB"))
    assert len(np.unique(rgb.reshape(-1, 3), axis=0)) > 50
    full, empty, off = (colour_counts(p) for p in panels(path, 3))
    for c in (full, empty, off):
        assert c["red"] > 10 and c["green"] > 30  # the chunk's cross, the robot
    assert full["blue"] > 500 and off["blue"] > 100
    assert empty["blue"] == 0  # nothing drawn for a masked row, even one within range
    assert full["orange"] > 30 and off["orange"] > 30  # the goal star (on the edge, with its arrow)


def test_storyboard_grid_and_multimodality(tmp_path):
    rng = np.random.default_rng(0)
    snaps = [{"obs": make_obs(humans=CROWD[: i % 4]), "chunk": CHUNK, "t": i * DT,
              "chunks": CHUNK + rng.normal(0, 0.3, (16, 5, 2))} for i in range(7)]
    story = Image.open(plot_storyboard(snaps, tmp_path / "grid.png", SENSING, DT))
    assert story.size == (5 * PANEL_W, 2 * PANEL_H + LEGEND_H)  # rows of five

    path = plot_multimodality(snaps[:4], tmp_path / "multi.png", SENSING, DT)
    assert Image.open(path).size == (4 * PANEL_W, PANEL_H + LEGEND_H)
    counts = [colour_counts(p) for p in panels(path, 4)]
    assert all(c["red"] > 50 and c["green"] > 100 for c in counts)  # 16 crosses each, a zoomed robot
    assert counts[0]["blue"] == 0 and all(c["blue"] > 300 for c in counts[1:])
    zoomed_out = plot_multimodality(snaps[:1], tmp_path / "wide.png", SENSING, DT, half_width=SENSING + 1)
    assert colour_counts(panels(zoomed_out, 1)[0])["green"] < counts[0]["green"]


def test_empty_snapshots_are_refused(tmp_path):
    with pytest.raises(ValueError, match="no snapshots"):
        plot_storyboard([], tmp_path / "x.png", SENSING, DT)


def test_finetune_curves_draw_an_itr_panel_only_for_runs_that_logged_it(tmp_path):
    """A run from before validation ran the intrusion test keeps its three panels (16 x 4 in at
    120 dpi); one that logged ``val/intrusion_rate`` gets a fourth, 5 in wider."""
    def records(itr):
        return [{"env_steps": s, "train/success_rate": 0.5, "train/episode_return": 1.0, "time/wall_s": s / 100,
                 "val/success_rate": 0.6, **({"val/intrusion_rate": itr} if itr is not None else {})}
                for s in (0, 1000, 2000)]

    old = Image.open(plot_finetune_curves({"old": records(None)}, tmp_path / "old.png")).size
    new = Image.open(plot_finetune_curves({"old": records(None), "new": records(0.05)}, tmp_path / "new.png")).size
    assert old == (16 * 120, 4 * 120) and new == (21 * 120, 4 * 120)


# -- end to end on a tiny checkpoint --------------------------------------------------------------
@pytest.fixture(scope="module")
def pretrained(tmp_path_factory) -> Path:
    return make_tiny_checkpoint(tmp_path_factory.mktemp("fig"), num_diffusion_steps=5)


SIM = CrowdSimConfig(task="BoundedCrowdNav-v0", compute_intrusion=False)
SEED = 2_000_000_000


def test_record_snapshots_shapes_and_determinism(pretrained):
    snaps = figures.record_snapshots(pretrained, SIM, SEED, [5, 0, 2], n_samples=4, policy_seed=1)
    assert [s["step"] for s in snaps] == [0, 2, 5]
    assert [s["t"] for s in snaps] == [0.0, 0.5, 1.25]
    first, _ = CrowdNavEnv(config=SIM.resolve()).reset(seed=SEED)
    np.testing.assert_array_equal(snaps[0]["obs"], first)
    for s in snaps:
        assert s["obs"].shape == (269,) and s["chunk"].shape == (5, 2) and s["chunks"].shape == (4, 5, 2)
        assert np.all(np.isfinite(s["chunks"])) and np.all(np.abs(s["chunks"]) <= 1.0 + 1e-5)  # m/s, v_pref 1
        assert not np.allclose(s["chunks"][0], s["chunks"][1])  # independent samples
    # The robot moved between the drawn steps (by the executed first actions).
    assert not np.allclose(structured(snaps[2]["obs"]).robot[:2], structured(snaps[0]["obs"]).robot[:2])

    again = figures.record_snapshots(pretrained, SIM, SEED, [0, 2, 5], n_samples=4, policy_seed=1)
    fewer = figures.record_snapshots(pretrained, SIM, SEED, [0, 2, 5], n_samples=2, policy_seed=1)
    other = figures.record_snapshots(pretrained, SIM, SEED, [0, 2, 5], n_samples=4, policy_seed=2)
    for a, b, c, d in zip(snaps, again, fewer, other, strict=True):
        np.testing.assert_array_equal(a["chunks"], b["chunks"])
        np.testing.assert_array_equal(a["chunk"], c["chunk"])  # n_samples does not change the episode
        np.testing.assert_array_equal(a["obs"], c["obs"])
    assert not np.allclose(snaps[0]["chunk"], other[0]["chunk"])


def test_record_snapshots_stops_at_the_episode_end(pretrained):
    snaps = figures.record_snapshots(pretrained, SIM, SEED, [0, 1000], n_samples=1)
    assert [s["step"] for s in snaps] == [0]
    with pytest.raises(ValueError, match="steps"):
        figures.record_snapshots(pretrained, SIM, SEED, [-1], n_samples=1)


def test_cli_writes_both_figures(pretrained, tmp_path, capsys):
    out = tmp_path / "figs"
    figures.main([f"--policy.path={pretrained}", "--env.task=BoundedCrowdNav-v0", "--env.compute_intrusion=false",
                  f"--seed={SEED}", "--steps=0,3,6", "--n_samples=6", f"--output_dir={out}"])
    printed = capsys.readouterr().out
    for name in ("storyboard.png", "multimodality.png"):
        assert str(out / name) in printed
        img = Image.open(out / name)
        assert img.size == (3 * PANEL_W, PANEL_H + LEGEND_H + TITLE_H)
        assert all(colour_counts(p)["red"] > 10 and colour_counts(p)["green"] > 30 for p in panels(out / name, 3))


@pytest.mark.parametrize("args, message", [
    (["--policy.path=/nonexistent/pretrained_model"], "no such directory"),
    ([], "--policy.path"),
    (["--steps=0,x"], "--steps"),
    (["--steps=4,2"], "--steps"),
    (["--steps=-1"], "--steps"),
    (["--steps="], "--steps"),
    (["--n_samples=0"], "n_samples"),
])
def test_cli_errors(pretrained, tmp_path, args, message):
    base = [] if any(a.startswith("--policy.path") for a in args) or args == [] else [f"--policy.path={pretrained}"]
    with pytest.raises(SystemExit) as err:
        figures.main([*base, *args, f"--output_dir={tmp_path}"])
    assert str(err.value).startswith("error: ") and message in str(err.value)
    assert not (tmp_path / "storyboard.png").exists()


def test_cli_help_describes_the_options(capsys):
    with pytest.raises(SystemExit) as err:
        figures.main(["--help"])
    assert err.value.code == 0
    text = capsys.readouterr().out
    assert "Chunks sampled per drawn step" in text and "--policy.path" in text and "--env.task" in text
