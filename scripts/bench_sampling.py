"""Success against denoising steps, and what one action costs: PDPO sampled with DDPM over all K
steps and with DDIM over fewer, on the same test seeds.

    python scripts/bench_sampling.py --policy.path=<BC pretrained_model> --task=BoundedCrowdNav-v0 \
        --ddim_steps 0 10 5 4 2 --episodes 500

For each sampler (0 = DDPM over the policy's K steps, n = DDIM over n): ``select_action``
latency for one robot (median over ``--calls`` calls on real observations, after warm-up), and
``lerobot-crowdnav-eval`` on the first ``--episodes`` test seeds (SR, collision rates, ITR).
Only a BC checkpoint can switch samplers (a fine-tuned one runs the sampler it was tuned with).
Give it the CPU alone: latencies double when another process computes.
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
from pathlib import Path


def latency_ms(path: str, ddim_steps: int, task: str, calls: int, threads: int) -> float:
    import gymnasium as gym
    import numpy as np
    import torch

    import lerobot_crowdnav  # noqa: F401  (registers the envs)
    from lerobot_crowdnav.measure.episodes import LearnedPolicy
    from lerobot_crowdnav.sim.config import SEED_SPLITS

    torch.set_num_threads(threads)
    env = gym.make(f"lerobot_crowdnav/{task}")
    obs, _ = env.reset(seed=SEED_SPLITS["test"][0])
    actor = LearnedPolicy(Path(path), "cpu", obs.shape[0], 0, True, ddim_steps)
    times = []
    fresh = True
    for i in range(calls + 10):
        start = time.perf_counter()
        action = actor(obs[None], np.array([fresh]))[0]
        if i >= 10:
            times.append(time.perf_counter() - start)
        obs, _, terminated, truncated, _ = env.step(action)
        fresh = terminated or truncated
        if fresh:
            obs, _ = env.reset()
    return 1000 * statistics.median(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--policy.path", dest="policy", required=True, help="a BC pretrained_model directory")
    ap.add_argument("--task", default="BoundedCrowdNav-v0", help="env task (default: BoundedCrowdNav-v0)")
    ap.add_argument("--ddim_steps", type=int, nargs="+", default=[0, 10, 5, 4, 2],
                    help="samplers to compare: 0 = DDPM over all K, n = DDIM over n steps (default: 0 10 5 4 2)")
    ap.add_argument("--episodes", type=int, default=500, help="test episodes per sampler (default 500)")
    ap.add_argument("--calls", type=int, default=200, help="timed select_action calls per sampler (default 200)")
    ap.add_argument("--threads", type=int, default=1, help="torch threads while timing one robot (default 1)")
    ap.add_argument("--output", type=Path, default=None, help="also write the rows as JSON here")
    args = ap.parse_args()
    from lerobot_crowdnav.checkpoint_files import POLICY_CONFIG
    from lerobot_crowdnav.evaluation.eval import main as eval_main

    rows = []
    for steps in args.ddim_steps:
        with tempfile.TemporaryDirectory() as tmp:
            eval_main([f"--policy.path={args.policy}", f"--policy.ddim_steps={steps}", f"--env.task={args.task}",
                       f"--eval.n_episodes={args.episodes}", "--eval.split=test", f"--output_dir={tmp}"])
            m = json.loads((Path(tmp) / "metrics.json").read_text())
        rows.append({"sampler": "DDPM" if steps == 0 else "DDIM", "steps": steps, "sr": m["sr"], "cr_human": m["cr_human"],
                     "cr_wall": m["cr_wall"], "itr": m["itr"], "eval_wall_s": m["wall_time_s"],
                     "latency_ms": latency_ms(args.policy, steps, args.task, args.calls, args.threads)})
    print(f"\n{args.task}, {args.episodes} test episodes, {args.policy}\n")
    print("| sampler | denoiser calls per action | SR (%) | human CR (%) | wall CR (%) | ITR (%) | select_action (ms, 1 robot) | eval wall time (s) |")
    print("|---|---|---|---|---|---|---|---|")
    k = json.loads((Path(args.policy) / POLICY_CONFIG).read_text())["num_diffusion_steps"]
    for r in rows:
        calls = r["steps"] or k
        print(f"| {r['sampler']} | {calls} | {100 * r['sr']:.1f} | {100 * r['cr_human']:.1f} | {100 * r['cr_wall']:.1f} | "
              f"{100 * r['itr']:.2f} | {r['latency_ms']:.2f} | {r['eval_wall_s']:.1f} |")
    if args.output:
        args.output.write_text(json.dumps(rows, indent=2))


if __name__ == "__main__":
    main()
