#!/usr/bin/env python
"""Data-loading throughput of a LeRobotDataset with and without ``lerobot_crowdnav.data.fast_loader``,
against PDPO's training step.

Measures, interleaving lerobot's own path (``orig``), the fast path (``fast``) and, for the
DataLoader, the fast reads item by item (``items``: without its batched ``__getitems__``) in
rotating order, ``--repeats`` times each, and reports medians:

* ``getitem``: samples/s of ``LeRobotDataset.__getitem__`` at random indices with PDPO's action
  chunk (``delta_timestamps={"action": [0, .25, .5, .75, 1]}``);
* ``loader``: samples/s of a ``torch.utils.data.DataLoader`` (``--batch-size``, shuffled) for each
  ``--workers`` count, workers started with ``--mp-context`` (lerobot-train's default: spawn),
  start-up and the first batches excluded;
* ``step``: seconds per PDPO training step on one batch: the pdpo preprocessor, then
  ``PDPOPolicy.forward`` + backward + AdamW step (+ EMA update, as lerobot-train does).

Example: ``timeout 1800 .venv/bin/python scripts/bench_loader.py --repeats 5 --output out.json``.
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import time
from pathlib import Path

import numpy as np
import torch

DEFAULT_ROOT = Path(__file__).resolve().parents[1] / "outputs/datasets/local/crowdnav_orca_success"


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--root", type=Path, default=DEFAULT_ROOT, help="LeRobotDataset root (default: %(default)s)")
    p.add_argument("--repo-id", default="local/crowdnav_orca_success", help="its repo_id (default: %(default)s)")
    p.add_argument("--repeats", type=int, default=5, help="timed runs per figure; medians (default: %(default)s)")
    p.add_argument("--samples", type=int, default=1000,
                   help="random __getitem__ calls per timed run (default: %(default)s)")
    p.add_argument("--batch-size", type=int, default=128, help="DataLoader / training batch (default: %(default)s)")
    p.add_argument("--workers", type=int, nargs="*", default=[0, 2],
                   help="DataLoader num_workers values (default: %(default)s)")
    p.add_argument("--batches", type=int, default=20,
                   help="DataLoader batches per timed run, after --warmup (default: %(default)s)")
    p.add_argument("--warmup", type=int, default=3, help="untimed first batches (default: %(default)s)")
    p.add_argument("--mp-context", default="spawn", help="worker start method (default: %(default)s)")
    p.add_argument("--steps", type=int, default=10, help="training steps per timed run (default: %(default)s)")
    p.add_argument("--what", nargs="*", default=["getitem", "loader", "step"],
                   choices=["getitem", "loader", "step"], help="what to measure (default: all)")
    p.add_argument("--threads", type=int, help="torch.set_num_threads in the main process (default: torch's)")
    p.add_argument("--output", type=Path, help="also write the results as JSON here")
    return p.parse_args(argv)


def set_mode(mode: str) -> None:
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from lerobot_crowdnav.data import fast_loader

    fast_loader.uninstall()
    if mode in ("fast", "items"):
        if not fast_loader.install():
            raise SystemExit("fast_loader.install() refused (lerobot version or LEROBOT_CROWDNAV_FAST_LOADER=0)")
    if mode == "items":
        del LeRobotDataset.__getitems__  # the DataLoader then reads item by item
    assert fast_loader.is_installed() == (mode == "fast")


def make_dataset(args, delta_timestamps):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    return LeRobotDataset(args.repo_id, root=args.root, delta_timestamps=delta_timestamps)


def time_getitem(ds, n: int, seed: int) -> float:
    idx = np.random.default_rng(seed).integers(0, len(ds), n).tolist()
    ds[idx[0]]
    start = time.perf_counter()
    for i in idx:
        ds[i]
    return n / (time.perf_counter() - start)


def time_loader(ds, args, workers: int, seed: int) -> float:
    kw = dict(num_workers=workers)
    if workers > 0:
        kw.update(multiprocessing_context=args.mp_context, prefetch_factor=2)
    loader = torch.utils.data.DataLoader(ds, batch_size=args.batch_size, shuffle=True, drop_last=True,
                                         generator=torch.Generator().manual_seed(seed), **kw)
    it = iter(loader)
    for _ in range(args.warmup):
        next(it)
    start = time.perf_counter()
    for _ in range(args.batches):
        next(it)
    rate = args.batches * args.batch_size / (time.perf_counter() - start)
    del it, loader
    return rate


def time_steps(ds, args, seed: int) -> dict:
    from lerobot_policy_pdpo import PDPOConfig, PDPOPolicy, make_pdpo_pre_post_processors
    from lerobot.configs.types import FeatureType, PolicyFeature

    torch.manual_seed(seed)
    feats = ds.meta.features
    cfg = PDPOConfig(input_features={"observation.state": PolicyFeature(FeatureType.STATE,
                                                                        tuple(feats["observation.state"]["shape"]))},
                     output_features={"action": PolicyFeature(FeatureType.ACTION, tuple(feats["action"]["shape"]))},
                     device="cpu")
    policy = PDPOPolicy(cfg).train()
    pre, _ = make_pdpo_pre_post_processors(cfg, ds.meta.stats)
    optimizer = cfg.get_optimizer_preset().build(policy.get_optim_params())
    loader = torch.utils.data.DataLoader(ds, batch_size=args.batch_size, shuffle=True,
                                         generator=torch.Generator().manual_seed(seed))
    raw = next(iter(loader))
    pre_times, step_times = [], []
    for k in range(args.steps + 2):
        t0 = time.perf_counter()
        batch = pre(dict(raw))
        t1 = time.perf_counter()
        loss, _ = policy.forward(batch)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        policy.update()
        t2 = time.perf_counter()
        if k >= 2:  # warm-up
            pre_times.append(t1 - t0)
            step_times.append(t2 - t1)
    return {"preprocessor_s": statistics.median(pre_times), "model_step_s": statistics.median(step_times)}


def main(argv=None) -> dict:
    args = parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    import lerobot
    from lerobot_crowdnav.cli import machine_description

    delta = {"action": [0.0, 0.25, 0.5, 0.75, 1.0]}
    ds = make_dataset(args, delta)
    result = {"machine": machine_description(), "python": platform.python_version(),
              "torch": torch.__version__, "lerobot": lerobot.__version__, "torch_threads": torch.get_num_threads(),
              "dataset": str(args.root), "frames": len(ds), "delta_timestamps": delta, "args": {
                  k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()}}
    runs: dict[str, list[float]] = {}

    def record(name: str, value: float) -> None:
        runs.setdefault(name, []).append(value)
        shown = f"{value * 1e3:10,.1f} ms" if name.startswith("step") else f"{value:10,.0f} samples/s"
        print(f"  {name:28s} {shown}", flush=True)

    for r in range(args.repeats):
        print(f"repeat {r + 1}/{args.repeats}", flush=True)
        modes = ["orig", "fast", "items"]
        for mode in modes[r % 3:] + modes[:r % 3]:
            set_mode(mode)
            if "getitem" in args.what and mode != "items":
                record(f"getitem {mode}", time_getitem(ds, args.samples, seed=r))
            if "loader" in args.what:
                for w in args.workers:
                    record(f"loader w={w} {mode}", time_loader(ds, args, w, seed=r))
        if "step" in args.what:
            set_mode("fast")
            for key, value in time_steps(ds, args, seed=r).items():
                record(f"step {key}", value)

    medians = {k: statistics.median(v) for k, v in runs.items()}
    result.update(runs=runs, medians=medians)
    lines = [f"{args.root.name}: {len(ds):,} frames; {result['machine']}; torch threads "
             f"{result['torch_threads']}; medians of {args.repeats} interleaved runs", ""]
    if "getitem" in args.what:
        o, f = medians["getitem orig"], medians["getitem fast"]
        lines.append(f"__getitem__ samples/s: lerobot {o:,.0f} ({1e3 / o:.3f} ms), fast {f:,.0f} "
                     f"({1e3 / f:.3f} ms), x{f / o:.1f}")
    step = None
    if "step" in args.what:
        step = medians["step model_step_s"] + medians["step preprocessor_s"]
        lines.append(f"PDPO step at batch {args.batch_size}: preprocessor {medians['step preprocessor_s'] * 1e3:.1f} ms"
                     f" + forward/backward/AdamW/EMA {medians['step model_step_s'] * 1e3:.1f} ms = "
                     f"{step * 1e3:.1f} ms ({args.batch_size / step:,.0f} samples/s)")
    if "loader" in args.what:
        for w in args.workers:
            o, i, f = (medians[f"loader w={w} {m}"] for m in ("orig", "items", "fast"))
            line = (f"DataLoader batch {args.batch_size}, num_workers={w}: lerobot {o:,.0f} samples/s "
                    f"({args.batch_size / o * 1e3:.1f} ms/batch), fast item by item {i:,.0f} samples/s "
                    f"({args.batch_size / i * 1e3:.1f} ms/batch), fast batched {f:,.0f} samples/s "
                    f"({args.batch_size / f * 1e3:.1f} ms/batch), x{f / o:.1f}")
            if step is not None:
                line += (f"; loader time / step time: lerobot {args.batch_size / o / step:.2f}, "
                         f"fast {args.batch_size / f / step:.2f}")
            lines.append(line)
    result["summary"] = "\n".join(lines)
    print("\n" + result["summary"], flush=True)
    if args.output:
        args.output.parent.mkdir(parents=True, exist_ok=True)
        args.output.write_text(json.dumps(result, indent=2))
    return result


if __name__ == "__main__":
    main()
