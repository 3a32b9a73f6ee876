"""The PDPO lerobot plugin: configuration, discovery, loss on real data, padding, sampling,
save/load, the sentinel-free statistics, and a short lerobot-train -> lerobot-eval round trip."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import draccus
import numpy as np
import pytest
import torch
from lerobot.configs.policies import PreTrainedConfig
from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from lerobot_policy_pdpo import PDPOConfig, PDPOPolicy, make_pdpo_pre_post_processors
from lerobot_policy_pdpo.processor_pdpo import crowd_state_stats

from lerobot_crowdnav.data.collect import main as collect_main

from fault_injection import ROOT, run_killed

REPO = "local/test_pdpo"
BIN = Path(sys.executable).parent
FEATURES = dict(input_features={"observation.state": PolicyFeature(FeatureType.STATE, (269,))},
                output_features={"action": PolicyFeature(FeatureType.ACTION, (2,))})


@dataclasses.dataclass
class _PolicyOnly:
    policy: PreTrainedConfig


def make_config(**kw) -> PDPOConfig:
    return PDPOConfig(**FEATURES, device="cpu", **kw)


@pytest.fixture(scope="module")
def dataset_root(tmp_path_factory):
    """A collection SIGKILLed mid-commit and resumed (issue 12: lerobot-train must read it)."""
    root = tmp_path_factory.mktemp("pdpo") / "ds"
    argv = ["--episodes=16", "--batch_size=8", f"--root={root}", f"--repo_id={REPO}"]
    run_killed([str(ROOT / "datasets_scripts/collect_orca.py"), *argv], "collect.renaming", 2)
    collect_main([*argv, "--resume=true"])
    return root


def test_parameter_counts_match_the_paper_within_10_percent():
    from lerobot_crowdnav.rl.dppo import ValueHead

    cfg = make_config()
    actor = PDPOPolicy(cfg).parameter_counts()["actor"]
    critic = sum(p.numel() for p in ValueHead(cfg.latent_dim, cfg.value_mlp_dims).parameters())
    assert abs(actor / 0.848e6 - 1) < 0.10, actor
    assert abs(critic / 0.201e6 - 1) < 0.10, critic


def test_config_round_trip_through_draccus(tmp_path):
    cfg = make_config(horizon=1, ema_decay=0.99, denoiser_dims=(64, 64))
    cfg._save_pretrained(tmp_path)
    loaded = PreTrainedConfig.from_pretrained(tmp_path)
    assert isinstance(loaded, PDPOConfig)
    assert (loaded.horizon, loaded.ema_decay, tuple(loaded.denoiser_dims)) == (1, 0.99, (64, 64))
    assert loaded.action_delta_indices == [0]

    parsed = draccus.parse(_PolicyOnly, args=["--policy.type=pdpo", "--policy.horizon=3",
                                             "--policy.n_action_steps=2"]).policy
    assert isinstance(parsed, PDPOConfig) and parsed.action_delta_indices == [0, 1, 2]
    with pytest.raises(ValueError, match="n_action_steps"):
        make_config(horizon=2, n_action_steps=3)


def test_lerobot_discovers_the_plugin():
    code = ("from lerobot.utils.import_utils import register_third_party_plugins; "
            "register_third_party_plugins(); "
            "from lerobot.configs.policies import PreTrainedConfig; "
            "from lerobot.policies.factory import get_policy_class, make_pre_post_processors; "
            "print(PreTrainedConfig.get_choice_class('pdpo').__name__, get_policy_class('pdpo').__name__)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=180)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split()[-2:] == ["PDPOConfig", "PDPOPolicy"]


def _batch(dataset_root, cfg, n=32):
    ds = LeRobotDataset(REPO, root=dataset_root, delta_timestamps={"action": [k / 4 for k in cfg.action_delta_indices]})
    pre, _ = make_pdpo_pre_post_processors(cfg, ds.meta.stats)
    loader = torch.utils.data.DataLoader(ds, batch_size=n, shuffle=True, generator=torch.Generator().manual_seed(0))
    return pre(next(iter(loader))), ds


def test_forward_backward_on_real_data_ignores_padding(dataset_root):
    torch.manual_seed(0)
    cfg = make_config()
    policy = PDPOPolicy(cfg)
    batch, _ = _batch(dataset_root, cfg, n=64)
    assert batch["action"].shape == (64, 5, 2) and batch["action"].abs().max() <= 1 + 1e-5
    loss, info = policy.forward(batch)
    loss.backward()
    assert torch.isfinite(loss) and info["denoise_mse"] > 0
    assert all(p.grad is not None for p in policy.get_optim_params())
    # The loss only sees non-padded steps: a wildly wrong noise prediction on padded steps
    # changes nothing, on a real step it does.
    batch["action_is_pad"][:, 3:] = True
    torch.manual_seed(1)
    a, _ = policy.forward(batch)
    original = policy.actor.denoiser.forward

    def corrupt(steps):
        def forward(x, k, z):
            out = original(x, k, z).clone()
            out[:, steps] += 1e6
            return out
        return forward

    policy.actor.denoiser.forward = corrupt(slice(3, None))
    torch.manual_seed(1)
    b, _ = policy.forward(batch)
    policy.actor.denoiser.forward = corrupt(slice(0, 1))
    torch.manual_seed(1)
    c, _ = policy.forward(batch)
    policy.actor.denoiser.forward = original
    assert torch.equal(a, b) and c > 1e6


def test_noise_draws_share_one_encoding_and_respect_padding(dataset_root):
    """noise_draws = D: the encoder runs once on B observations, the denoiser on D x B noised
    chunks (each observation's padding mask repeated); D = 1 is the paper's loss."""
    torch.manual_seed(0)
    cfg = make_config(noise_draws=4)
    policy = PDPOPolicy(cfg)
    batch, _ = _batch(dataset_root, cfg, n=16)
    batch["action_is_pad"][:, 4:] = True
    seen = {}
    enc, den = policy.actor.encoder.forward, policy.actor.denoiser.forward
    policy.actor.encoder.forward = lambda s: seen.setdefault("enc", s.shape[0]) and enc(s)
    policy.actor.denoiser.forward = lambda x, k, z: seen.setdefault("den", x.shape[0]) and den(x, k, z)
    loss, _ = policy.forward(batch)
    assert seen == {"enc": 16, "den": 64} and torch.isfinite(loss)
    policy.actor.encoder.forward = enc
    # Padded steps of every draw stay out of the loss.
    torch.manual_seed(1)
    a, _ = policy.forward(batch)
    policy.actor.denoiser.forward = lambda x, k, z: den(x, k, z) + torch.tensor([0, 0, 0, 0, 1e6])[None, :, None]
    torch.manual_seed(1)
    b, _ = policy.forward(batch)
    assert torch.equal(a, b)
    with pytest.raises(ValueError, match="noise_draws"):
        make_config(noise_draws=0)


def test_the_denoiser_shares_one_latent_among_consecutive_rows():
    """z with one row per r consecutive rows of x (a state's noise draws, a chain's transitions):
    the same noise predictions and gradients as z repeated r times, the latent's share of the
    first layer computed once per latent; rows that cannot share evenly are refused."""
    torch.manual_seed(0)
    den = PDPOPolicy(make_config()).actor.denoiser
    x, k = torch.randn(60, 5, 2), torch.randint(0, 20, (60,))
    z = torch.randn(12, 256, requires_grad=True)

    def out_and_grads(latent):
        den.zero_grad()
        z.grad = None
        out = den(x, k, latent)
        (out * torch.linspace(-1, 1, out.numel()).view_as(out)).sum().backward()
        return out.detach(), z.grad.clone(), {n: p.grad.clone() for n, p in den.named_parameters()}

    shared, repeated = out_and_grads(z), out_and_grads(z.repeat_interleave(5, dim=0))
    torch.testing.assert_close(shared[0], repeated[0], rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(shared[1], repeated[1], rtol=1e-4, atol=1e-5)
    for n in repeated[2]:
        torch.testing.assert_close(shared[2][n], repeated[2][n], rtol=1e-4, atol=1e-5)
    with pytest.raises(ValueError, match="cannot share"):
        den(x, k, z[:7])


def test_velocity_dropout_hides_the_robot_velocity_from_the_encoder():
    """velocity_dropout = 1: the latent does not depend on entries 7-8 (the previous action), in
    training and acting alike; 0 < p < 1 drops them for about a fraction p of the training
    samples and never when acting; 0 (the paper) always reads them. The other 7 robot floats
    are never touched."""
    torch.manual_seed(0)
    b = 4000
    state = torch.randn(b, 269)
    state[:, 249:] = (torch.rand(b, 20) < 0.5).float()
    other = state.clone()
    other[:, 7:9] += 3.0
    moved = state.clone()
    moved[:, 3:5] += 3.0  # the goal
    for p in (0.0, 0.3, 1.0):
        enc = PDPOPolicy(make_config(velocity_dropout=p, dropout=0.0)).actor.encoder
        for training in (True, False):
            enc.train(training)
            torch.manual_seed(1)
            a = enc(state)
            torch.manual_seed(1)
            changed = (enc(other) - a).abs().amax(dim=1) > 1e-6
            torch.manual_seed(1)
            assert ((enc(moved) - a).abs().amax(dim=1) > 1e-6).all()  # the goal always counts
            dropped = 1 - changed.float().mean().item()
            expected = p if (training or p == 1.0) else 0.0
            assert abs(dropped - expected) < 0.03, (p, training, dropped)
    with pytest.raises(ValueError, match="velocity_dropout"):
        make_config(velocity_dropout=1.5)


def test_training_encodes_only_the_visible_prefix_with_the_same_values_and_gradients(monkeypatch):
    """With gradients on (lerobot-train, the PPO update) the encoder runs its per-human part on
    each row's visible prefix only, in groups of similar counts (speed); the latent and every
    parameter's gradient equal those of running all 20 slots, which the same humans in reversed
    slots (not a prefix: the encoder is symmetric in the humans) and acting without gradients
    both do. Counts 0 to 20, nobody visible included."""
    torch.manual_seed(0)
    b, n = 300, 20
    count = torch.arange(b) % (n + 1)
    state = torch.randn(b, 269)
    state[:, 249:] = (torch.arange(n) < count[:, None]).float()
    rows = state[:, 9:249].reshape(b, n, 12).clone()
    rows[state[:, 249:] == 0] = 4.0  # a sentinel in normalized units
    state[:, 9:249] = rows.flatten(1)
    reversed_slots = state.clone()
    reversed_slots[:, 9:249] = rows.flip(1).flatten(1)
    reversed_slots[:, 249:] = state[:, 249:].flip(1)
    enc = PDPOPolicy(make_config(dropout=0.0)).actor.encoder.train()
    widths = []
    pool = enc._pool
    monkeypatch.setattr(enc, "_pool", lambda humans, *a: widths.append(humans.shape[1]) or pool(humans, *a))

    def latent_and_grads(x):
        enc.zero_grad()
        z = enc(x)
        (z * torch.linspace(-1, 1, z.shape[1])).sum().backward()
        return z.detach(), {k: p.grad.clone() for k, p in enc.named_parameters()}

    z_prefix, g_prefix = latent_and_grads(state)
    assert len(widths) > 1 and min(widths) < n  # grouped, narrower than every slot
    widths.clear()
    z_all, g_all = latent_and_grads(reversed_slots)
    assert widths == [n]
    with torch.no_grad():
        z_acting = enc(state)
    assert widths == [n, n]
    torch.testing.assert_close(z_prefix, z_all, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(z_prefix, z_acting, rtol=1e-5, atol=1e-5)
    for k in g_all:  # float32 sums in another order: equal to 1e-4 of each gradient's scale (a bias
        # that softmax ignores has a zero gradient, up to rounding)
        assert (g_prefix[k] - g_all[k]).abs().max() <= 3e-4 * g_all[k].abs().max() + 1e-6, k


def test_sentinel_rows_do_not_distort_state_statistics():
    cfg = make_config()
    rng = np.random.default_rng(0)
    n_frames, n = 4000, cfg.num_humans
    visible = rng.random((n_frames, n)) < np.linspace(0.9, 0.05, n)  # far rows rarely visible
    rows = rng.normal(2.0, 1.5, (n_frames, n, 12))
    rows[~visible] = cfg.sentinel_value
    state = np.concatenate([rng.normal(size=(n_frames, 9)), rows.reshape(n_frames, -1), visible], axis=1)
    stats = crowd_state_stats({"mean": state.mean(0), "std": state.std(0)}, cfg)
    vis_values = rows[visible]  # (visible rows, 12)
    np.testing.assert_allclose(stats["mean"][9:249].reshape(n, 12), np.tile(vis_values.mean(0), (n, 1)), rtol=1e-9)
    np.testing.assert_allclose(stats["std"][9:249].reshape(n, 12), np.tile(vis_values.std(0), (n, 1)), rtol=1e-9)
    assert np.all(stats["mean"][249:] == 0) and np.all(stats["std"][249:] == 1)
    np.testing.assert_array_equal(stats["mean"][:9], state.mean(0)[:9])
    again = crowd_state_stats(stats, cfg)  # idempotent on corrected statistics
    np.testing.assert_array_equal(again["mean"], stats["mean"])


def test_sampling_shapes_determinism_and_no_nan_without_humans(dataset_root):
    cfg = make_config()
    policy = PDPOPolicy(cfg).eval()
    batch, _ = _batch(dataset_root, cfg, n=8)
    torch.manual_seed(3)
    a = policy.predict_action_chunk(batch)
    torch.manual_seed(3)
    b = policy.predict_action_chunk(batch)
    assert a.shape == (8, 5, 2) and torch.equal(a, b) and a.abs().max() <= 1
    many = policy.sample_chunks(batch, num_samples=6, generator=torch.Generator().manual_seed(0))
    assert many.shape == (8, 6, 5, 2)
    assert many[:, 0].ne(many[:, 1]).any()  # different samples for one observation
    policy.reset()
    assert policy.select_action(batch).shape == (8, 2)
    empty = batch["observation.state"].clone()
    empty[:, 249:] = 0.0  # nobody visible
    out = policy.predict_action_chunk({"observation.state": empty})
    assert torch.isfinite(out).all()
    encoder = policy.actor.encoder  # with nobody visible the pooled crowd vector is exactly 0
    pooled = encoder._pool(torch.randn(8, encoder.n, encoder.row), torch.zeros(8, encoder.n, dtype=torch.bool),
                           torch.randn(8, 9))
    assert torch.equal(pooled, torch.zeros_like(pooled))
    policy.train()
    loss, _ = policy.forward({**batch, "observation.state": empty})
    assert torch.isfinite(loss)


def test_save_load_equality_including_ema(dataset_root, tmp_path):
    cfg = make_config(ema_start_step=0)
    policy = PDPOPolicy(cfg)
    batch, _ = _batch(dataset_root, cfg, n=8)
    opt = torch.optim.AdamW(policy.get_optim_params(), lr=1e-3)
    for _ in range(3):
        loss, _ = policy.forward(batch)
        opt.zero_grad()
        loss.backward()
        opt.step()
        policy.update()
    assert not torch.equal(policy.ema.denoiser.net[0].weight, policy.actor.denoiser.net[0].weight)
    policy.save_pretrained(tmp_path)
    assert not list(tmp_path.glob("*.bin")) and not list(tmp_path.glob("*.pt"))  # safetensors only
    loaded = PDPOPolicy.from_pretrained(tmp_path).eval()
    policy.eval()
    for a, b in zip(policy.state_dict().values(), loaded.state_dict().values(), strict=True):
        assert torch.equal(a, b)
    torch.manual_seed(5)
    x = policy.predict_action_chunk(batch)
    torch.manual_seed(5)
    y = loaded.predict_action_chunk(batch)
    assert torch.equal(x, y)


def test_lerobot_train_then_lerobot_eval(dataset_root, tmp_path):
    out = tmp_path / "train"
    train = subprocess.run(
        [str(BIN / "lerobot-train"), "--policy.type=pdpo", f"--dataset.repo_id={REPO}",
         f"--dataset.root={dataset_root}", "--policy.push_to_hub=false", f"--output_dir={out}",
         "--steps=20", "--batch_size=32", "--save_freq=20", "--log_freq=10", "--num_workers=0",
         "--policy.device=cpu", "--wandb.enable=false"],
        capture_output=True, text=True, timeout=600)
    assert train.returncode == 0, train.stderr[-3000:]
    ckpt = out / "checkpoints" / "000020" / "pretrained_model"
    names = {p.name for p in ckpt.iterdir()}
    assert {"config.json", "model.safetensors", "train_config.json", "policy_preprocessor.json",
            "policy_postprocessor.json"} <= names
    assert json.loads((ckpt / "config.json").read_text())["type"] == "pdpo"
    optimizer = json.loads((ckpt / "train_config.json").read_text())["optimizer"]
    assert optimizer["type"] == "pdpo_adamw" and optimizer["fused"] is True  # the policy's preset
    # Starting from the checkpoint with a dataset: lerobot-train swaps in the dataset's raw
    # statistics, whose normalized mask would hide the nearest humans; PDPO refuses them.
    again = subprocess.run(
        [str(BIN / "lerobot-train"), f"--policy.path={ckpt}", f"--dataset.repo_id={REPO}",
         f"--dataset.root={dataset_root}", "--policy.push_to_hub=false", f"--output_dir={tmp_path / 'again'}",
         "--steps=2", "--batch_size=8", "--num_workers=0", "--policy.device=cpu", "--wandb.enable=false"],
        capture_output=True, text=True, timeout=600)
    assert again.returncode != 0 and "visibility mask is not 0/1" in again.stderr, again.stderr[-3000:]
    ev = subprocess.run(
        [str(BIN / "lerobot-eval"), f"--policy.path={ckpt}", "--env.type=crowdnav",
         "--env.task=BoundedCrowdNav-v0", "--eval.n_episodes=2", "--eval.batch_size=2",
         "--policy.device=cpu", f"--output_dir={tmp_path / 'eval'}", "--seed=2000000000"],
        capture_output=True, text=True, timeout=600)
    assert ev.returncode == 0, ev.stderr[-3000:]
    info = json.loads((tmp_path / "eval" / "eval_info.json").read_text())
    assert info["per_group"]["crowdnav"]["n_episodes"] == 2
    assert len(info["per_task"][0]["metrics"]["successes"]) == 2

    # lerobot-crowdnav-eval with the checkpoint: full metrics on test seeds.
    from lerobot_crowdnav.evaluation.eval import main as eval_main
    from lerobot_crowdnav.data.hub import push_policy_to_dir

    eval_main([f"--policy.path={ckpt}", "--eval.n_episodes=4", "--eval.batch_size=2",
               f"--output_dir={tmp_path / 'crowdnav_eval'}"])
    metrics = json.loads((tmp_path / "crowdnav_eval" / "metrics.json").read_text())
    assert metrics["n_episodes"] == 4 and metrics["policy"] == "train@000020"
    from lerobot_crowdnav.measure.episodes import LearnedPolicy

    with_ema, raw = LearnedPolicy(ckpt, "cpu", 269), LearnedPolicy(ckpt, "cpu", 269, use_ema=False)  # --policy.use_ema
    assert with_ema.policy.sampling_actor() is with_ema.policy.ema
    assert raw.policy.sampling_actor() is raw.policy.actor
    with pytest.raises(SystemExit, match="no config.json"):
        eval_main([f"--policy.path={tmp_path}", f"--output_dir={tmp_path / 'bad'}"])
    with pytest.raises(SystemExit, match="observation.state of shape"):
        eval_main([f"--policy.path={ckpt}", "--env.num_humans=5", f"--output_dir={tmp_path / 'bad2'}"])

    # Hub-format model directory: what a Hub model repo holds, loadable by lerobot-eval and
    # from_pretrained with identical weights.
    repo = push_policy_to_dir(ckpt, "local/pdpo_tiny", tmp_path / "hub", metrics_path=tmp_path / "crowdnav_eval" / "metrics.json")
    assert repo == tmp_path / "hub" / "models" / "local" / "pdpo_tiny"
    names = {p.name for p in repo.iterdir()}
    assert {"README.md", "config.json", "model.safetensors", "train_config.json", "policy_preprocessor.json",
            "policy_postprocessor.json"} <= names
    assert not any(n.endswith((".bin", ".pt", ".pkl")) for n in names)
    card = (repo / "README.md").read_text()
    assert card.startswith("---\n") and "library_name: lerobot" in card and "0.848 M" in card and "| SR (%)" in card
    a, b = PDPOPolicy.from_pretrained(ckpt), PDPOPolicy.from_pretrained(repo)
    for x, y in zip(a.state_dict().values(), b.state_dict().values(), strict=True):
        assert torch.equal(x, y)
    ev = subprocess.run(
        [str(BIN / "lerobot-eval"), f"--policy.path={repo}", "--env.type=crowdnav", "--eval.n_episodes=1",
         "--eval.batch_size=1", "--policy.device=cpu", f"--output_dir={tmp_path / 'eval_hub'}"],
        capture_output=True, text=True, timeout=600)
    assert ev.returncode == 0, ev.stderr[-3000:]
    with pytest.raises(FileExistsError):
        push_policy_to_dir(ckpt, "local/pdpo_tiny", tmp_path / "hub")
    (ckpt / "stale.pt").write_bytes(b"pickle")
    with pytest.raises(ValueError, match="pickled"):
        push_policy_to_dir(ckpt, "local/pdpo_tiny", tmp_path / "hub", overwrite=True)
