"""Diffusion-PPO throughput per setting: rollout, update and overall env-steps/s.

    python scripts/bench_finetune.py --policy.path=<BC pretrained_model> \
        --setting "paper=" --setting "frozen encoder=--ppo.freeze_encoder=true" --repeats 2

Each setting runs ``lerobot-crowdnav-finetune`` for ``--iterations`` actor updates after the
critic warm-up (64 envs x 64 steps each by default) in a fresh process, settings interleaved over
the repeats; the figure is the median over the timed iterations of all repeats (the warm-up
iteration, which trains no actor, is left out). Give it the CPU alone: another busy process
halves these numbers.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

KEYS = {"rollout": "perf/rollout_env_steps_per_s", "update": "perf/update_env_steps_per_s",
        "overall": "perf/env_steps_per_s"}


def run_setting(policy: str, flags: list[str], num_envs: int, n_steps: int, iterations: int, task: str) -> list[dict]:
    per_iter = num_envs * n_steps
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "run"
        cmd = [str(Path(sys.executable).parent / "lerobot-crowdnav-finetune"), f"--policy.path={policy}",
               f"--env.task={task}", f"--num_envs={num_envs}", f"--ppo.n_steps={n_steps}",
               f"--env_steps={per_iter * (iterations + 1)}", "--val.freq=0", "--val.n_episodes=4",
               "--save_freq=1000000000", "--ppo.n_critic_warmup_itr=1", f"--output_dir={out}", *flags]
        done = subprocess.run(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        if done.returncode:
            raise SystemExit(f"{' '.join(cmd)} failed:\n{done.stderr[-2000:]}")
        records = [json.loads(line) for line in (out / "progress.jsonl").read_text().splitlines()]
    return [r for r in records if r.get("critic_warmup") == 0.0 and KEYS["overall"] in r]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--policy.path", dest="policy", required=True, help="BC pretrained_model directory to fine-tune")
    ap.add_argument("--setting", action="append", required=True,
                    help='"name=flags": a label and the fine-tuning flags it adds (space-separated; may be empty)')
    ap.add_argument("--task", default="BoundedCrowdNav-v0", help="env task (default: BoundedCrowdNav-v0)")
    ap.add_argument("--num_envs", type=int, default=64, help="envs (default 64)")
    ap.add_argument("--n_steps", type=int, default=64, help="rollout length per iteration (default 64)")
    ap.add_argument("--iterations", type=int, default=3, help="timed iterations per run (default 3)")
    ap.add_argument("--repeats", type=int, default=2, help="runs per setting, interleaved (default 2)")
    args = ap.parse_args()
    settings = []
    for s in args.setting:
        name, sep, flags = s.partition("=")
        if not sep or not name:
            ap.error(f"--setting must be name=flags, got {s!r}")
        settings.append((name, flags.split()))
    seen: dict[str, list[dict]] = {name: [] for name, _ in settings}
    for _ in range(args.repeats):
        for name, flags in settings:
            seen[name] += run_setting(args.policy, flags, args.num_envs, args.n_steps, args.iterations, args.task)
    print(f"| setting | rollout | update | overall | (env-steps/s, median of {args.repeats} x {args.iterations} iterations) |")
    print("|---|---|---|---|---|")
    for name, flags in settings:
        med = {k: statistics.median(r[key] for r in seen[name]) for k, key in KEYS.items()}
        print(f"| {name} (`{' '.join(flags) or 'defaults'}`) | {med['rollout']:,.0f} | {med['update']:,.0f} | "
              f"{med['overall']:,.0f} | |")


if __name__ == "__main__":
    main()
