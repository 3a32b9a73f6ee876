"""BC training throughput of the PDPO policy on this machine: samples/s of one lerobot-style
optimizer step (denoising loss, backward, the policy's AdamW preset, EMA) for each setting, interleaved repeats,
medians. Data: random normalized states with a realistic visibility mask (the loader is measured
by scripts/bench_loader.py).

    python scripts/bench_bc.py --threads 2 --repeats 5
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from lerobot_crowdnav.layout import mask_slice, obs_dim


def make_policy(**overrides):
    from lerobot.configs.types import FeatureType, PolicyFeature
    from lerobot_policy_pdpo import PDPOConfig, PDPOPolicy

    cfg = PDPOConfig(input_features={"observation.state": PolicyFeature(FeatureType.STATE, (obs_dim(20, 5),))},
                     output_features={"action": PolicyFeature(FeatureType.ACTION, (2,))}, device="cpu", **overrides)
    return PDPOPolicy(cfg)


def batch(b: int, horizon: int, gen: torch.Generator) -> dict:
    state = torch.randn(b, obs_dim(20, 5), generator=gen)
    n_vis = torch.randint(0, 21, (b, 1), generator=gen)
    state[:, mask_slice(20, 5)] = (torch.arange(20)[None] < n_vis).float()
    return {"observation.state": state, "action": torch.rand(b, horizon, 2, generator=gen) * 2 - 1,
            "action_is_pad": torch.zeros(b, horizon, dtype=torch.bool)}


def time_setting(b: int, draws: int, bf16: bool, compiled: bool, steps: int, horizon: int) -> float:
    policy = make_policy(horizon=horizon, noise_draws=draws)
    if compiled:  # inductor over the encoder's per-group part, where a step's many small operations are
        encoder = policy.actor.encoder
        encoder._pool = torch.compile(encoder._pool, dynamic=True)
    opt = policy.config.get_optimizer_preset().build(policy.get_optim_params())  # what lerobot-train builds
    gen = torch.Generator().manual_seed(0)
    data = [batch(b, horizon, gen) for _ in range(4)]

    def step(i: int) -> None:
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
            loss, _ = policy.forward(data[i % 4])
        opt.zero_grad()
        loss.backward()
        opt.step()
        policy.update()

    for i in range(30 if compiled else 3):  # a compiled setting also compiles its group shapes first
        step(i)
    start = time.perf_counter()
    for i in range(steps):
        step(i)
    return steps * b / (time.perf_counter() - start)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--threads", type=int, default=torch.get_num_threads(), help="torch intra-op threads")
    ap.add_argument("--repeats", type=int, default=3, help="interleaved timed runs per setting (median)")
    ap.add_argument("--steps", type=int, default=20, help="optimizer steps per timed run")
    ap.add_argument("--horizon", type=int, default=5, help="action chunk H")
    ap.add_argument("--settings", default="128:1:0,128:4:0,256:1:0,512:1:0,128:1:1",
                    help="comma-separated batch:noise_draws:bf16[:compile] settings (bf16 autocast and "
                         "torch.compile of the crowd encoder's per-group part: 0 or 1; compile defaults to 0)")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    try:
        settings = [tuple(int(x) for x in s.split(":")) for s in args.settings.split(",")]
    except ValueError:
        ap.error(f"--settings={args.settings}: integers batch:noise_draws:bf16[:compile] expected")
    if any(len(s) not in (3, 4) for s in settings):
        ap.error(f"--settings={args.settings}: each setting has 3 or 4 fields, batch:noise_draws:bf16[:compile]")
    settings = [(*s, 0)[:4] for s in settings]
    results: dict[tuple, list[float]] = {s: [] for s in settings}
    for _ in range(args.repeats):
        for s in settings:
            results[s].append(time_setting(s[0], s[1], bool(s[2]), bool(s[3]), args.steps, args.horizon))
    print(f"torch {torch.__version__}, {args.threads} threads")
    print("| batch | noise draws | bf16 autocast | torch.compile | samples/s (median) | steps/s |")
    print("|---|---|---|---|---|---|")
    for (b, d, bf, comp), v in results.items():
        med = statistics.median(v)
        print(f"| {b} | {d} | {'yes' if bf else 'no'} | {'yes' if comp else 'no'} | {med:,.0f} | {med / b:.1f} |")


if __name__ == "__main__":
    main()
