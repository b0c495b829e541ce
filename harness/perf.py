"""Speed and memory figures (`make bench-train`, `make bench-methods`, `make bench-eval`).

Targets are printed beside the measurements; nothing here asserts, so a slow machine gives
slow figures, not a failing test.
"""

from __future__ import annotations

import copy
import json
import os
import statistics
import subprocess
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context

import torch

from harness.config import load_benchmark
from harness.datasets import TrainingData
from harness.evaluation import EnvCache, EvalSettings, Evaluator, evaluation_episodes
from harness.trainer import PhaseTimer, TrainSettings, train_stage
from methods import TaskContext, get_method, method_names
from policies import FlowMatchingConfig, FlowMatchingPolicy
from suites.base import run_expert_episode

STATE_DIM, ACTION_DIM = 39, 4  # Meta-World's


def synthetic_data(n: int, seed: int, task: str = "task", chunk: int = 4) -> TrainingData:
    g = torch.Generator().manual_seed(seed)
    return TrainingData({"state": torch.randn(n, STATE_DIM, generator=g)},
                        torch.randn(n, chunk, ACTION_DIM, generator=g).clamp(-1, 1),
                        torch.ones(n, chunk, dtype=torch.bool), torch.zeros(n, dtype=torch.long),
                        torch.randn(1, 384, generator=g), [task])


def _policy(size: str, image_keys: tuple[str, ...] = (), image_size: int = 84) -> FlowMatchingPolicy:
    torch.manual_seed(0)
    return FlowMatchingPolicy(FlowMatchingConfig(STATE_DIM, ACTION_DIM, size=size,
                                                 image_keys=image_keys, image_size=image_size))


def _ready_method(name: str, policy, foundation: TrainingData, task: TrainingData):
    method = get_method(name)()
    method.after_task(TaskContext(0, "foundation", foundation, policy, 0.05, 0))
    return method, TaskContext(1, "task", task, policy, 0.05, 0)


def bench_train(steps: int = 200, batch_size: int = 256) -> None:
    print(f"training throughput (batch {batch_size}, {steps} steps, {torch.get_num_threads()} thread)")
    print("| policy | parameters | samples/s | step ms | outside forward+backward "
          "| of which clip+AdamW | of which data+loop |")
    print("|---|---|---|---|---|---|---|")
    for size in ("tiny", "default"):
        policy = _policy(size)
        data = synthetic_data(20_000, 0)
        ctx = TaskContext(1, "task", data, policy, 0.05, steps)
        g = torch.Generator().manual_seed(0)
        train_stage(ctx, get_method("sft")(), TrainSettings(20, batch_size, 3e-4), g)  # warm-up
        timer = PhaseTimer()
        start = time.perf_counter()
        train_stage(ctx, get_method("sft")(), TrainSettings(steps, batch_size, 3e-4), g, timer=timer)
        total = time.perf_counter() - start
        share = {k: v / total for k, v in timer.seconds.items()}
        outside = 1 - share.get("forward", 0) - share.get("backward", 0)
        update = share.get("optimizer", 0)
        n_params = sum(p.numel() for p in policy.parameters())
        print(f"| {size} | {n_params:,} | {steps * batch_size / total:,.0f} | "
              f"{1000 * total / steps:.1f} | {100 * outside:.1f}% (target < 10%) | "
              f"{100 * update:.1f}% | {100 * (outside - update):.1f}% |")


def _rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def _method_memory(name: str, steps: int) -> dict:
    """Run in a fresh process: peak resident memory growth from before the method exists to
    the end of its training steps (its kept state, optimizer, activations), and its own state."""
    torch.set_num_threads(1)
    policy = _policy("default")
    foundation, task = synthetic_data(6000, 1, "foundation"), synthetic_data(6000, 2)
    base = peak = _rss_mb()
    method, ctx = _ready_method(name, policy, foundation, task)

    def sample(done: int) -> None:
        nonlocal peak
        peak = max(peak, _rss_mb())

    train_stage(ctx, method, TrainSettings(steps, 256, 3e-4), torch.Generator().manual_seed(0),
                after_step=sample)
    state_bytes = sum(t.numel() * t.element_size() for t in _tensors(method.state_dict()))
    return {"peak_rss_growth_mb": peak - base, "state_mb": state_bytes / 2**20}


def _tensors(obj):
    if isinstance(obj, torch.Tensor):
        yield obj
    elif isinstance(obj, dict):
        for v in obj.values():
            yield from _tensors(v)
    elif isinstance(obj, (list, tuple)):
        for v in obj:
            yield from _tensors(v)
    elif isinstance(obj, TrainingData):
        yield from _tensors([obj.obs, obj.actions, obj.action_mask, obj.task_index,
                             obj.instruction_table])


def bench_methods(rounds: int = 15, steps: int = 20) -> None:
    """Step time of every method, interleaved round by round so machine drift cancels out."""
    names = ["sft"] + [n for n in method_names() if n != "sft"]
    foundation, task = synthetic_data(6000, 1, "foundation"), synthetic_data(6000, 2)
    base = _policy("default")
    runs = {}
    for name in names:
        policy = copy.deepcopy(base)
        method, ctx = _ready_method(name, policy, foundation, task)
        runs[name] = (method, ctx)
        train_stage(ctx, method, TrainSettings(5, 256, 3e-4), torch.Generator().manual_seed(0))
    times: dict[str, list[float]] = {n: [] for n in names}
    for r in range(rounds):
        for name in names:
            method, ctx = runs[name]
            timer = PhaseTimer()  # the steps only: not before_task/after_task (a Fisher, say)
            train_stage(ctx, method, TrainSettings(steps, 256, 3e-4), torch.Generator().manual_seed(r),
                        timer=timer)
            step_time = sum(v for k, v in timer.seconds.items() if k != "other")
            times[name].append(step_time / steps)
    memory = {}
    for name in names:
        out = subprocess.run([sys.executable, "-m", "harness.perf", "_memory", name],
                             capture_output=True, text=True, check=True)
        memory[name] = json.loads(out.stdout.strip().splitlines()[-1])
    sft_time = statistics.median(times["sft"])
    sft_mem = max(memory["sft"]["peak_rss_growth_mb"], 1e-9)
    print(f"methods on the default policy (batch 256; step time: median of {rounds} interleaved "
          f"rounds of {steps} steps; memory: peak resident growth from before the method is built "
          f"to the end of training, in a fresh process each)")
    print("| method | step ms | time vs sft | peak RSS growth MB | memory vs sft | state held MB |")
    print("|---|---|---|---|---|---|")
    for name in names:
        t = statistics.median(times[name])
        m = memory[name]
        print(f"| {name} | {1000 * t:.1f} | {t / sft_time:.3f}x | {m['peak_rss_growth_mb']:.1f} | "
              f"{m['peak_rss_growth_mb'] / sft_mem:.2f}x | {m['state_mb']:.2f} |")
    print("target: consft within 1.05x of sft in time, and no parameter-sized state")


_RAW_ENVS: dict[tuple, EnvCache] = {}  # per worker process, kept between calls like the evaluator's


def _raw_expert_share(suite_name: str, episodes, max_steps: int, cameras: bool = False,
                      image_size: int = 84) -> int:
    from suites import get_suite

    key = (suite_name, cameras, image_size)
    if key not in _RAW_ENVS:
        _RAW_ENVS[key] = EnvCache(get_suite(suite_name), EvalSettings(
            len(episodes), max_steps, n_action_steps=1, cameras=cameras, image_size=image_size))
    envs = _RAW_ENVS[key]
    return sum(run_expert_episode(envs.for_task(ep.task, 1)[0], ep.seed, max_steps).steps
               for ep in episodes)


def bench_eval(workers: int = 2, episodes: int = 10, max_steps: int = 200, cameras: bool = False,
               image_size: int = 84, device: str = "cpu", central_policy: bool | None = None) -> None:
    """Evaluation env steps/s against raw expert stepping (with the same rendering: raw
    step-plus-render throughput when cameras are on); 1 -> 2 worker speed-up. A policy on an
    accelerator is evaluated with one central policy and simulators in the workers."""
    from suites import get_suite
    from suites.base import CAMERA_KEYS

    suite = get_suite("metaworld")
    benchmark = load_benchmark("mw-quick")
    mw_quick_tasks = benchmark.foundation_tasks + benchmark.stream_tasks
    eps = evaluation_episodes("metaworld", mw_quick_tasks, episodes)
    settings = EvalSettings(episodes, max_steps, n_action_steps=4, cameras=cameras,
                            image_size=image_size)
    ctx = get_context("spawn")
    render = [cameras] * workers, [image_size] * workers
    with ProcessPoolExecutor(workers, mp_context=ctx) as pool:  # warm: imports and env builds
        shares = [eps[i::workers] for i in range(workers)]
        list(pool.map(_raw_expert_share, ["metaworld"] * workers, shares, [1] * workers, *render))
        start = time.perf_counter()
        raw_steps = sum(pool.map(_raw_expert_share, ["metaworld"] * workers, shares,
                                 [max_steps] * workers, *render))
        raw_time = time.perf_counter() - start
    image_keys = CAMERA_KEYS if cameras else ()
    policy = _policy("default", image_keys, image_size).to(resolve_device(device))
    instructions = {t: torch.randn(384).numpy() for t in mw_quick_tasks}
    rates, layouts = {}, {}
    for n in (1, workers):
        with Evaluator(suite, settings, workers=n, central_policy=central_policy) as evaluator:
            layouts[n] = evaluator.layout(policy)
            evaluator.evaluate(policy, mw_quick_tasks, instructions, noise_seed=0)  # warm
            start = time.perf_counter()
            results = evaluator.evaluate(policy, mw_quick_tasks, instructions, noise_seed=0)
            elapsed = time.perf_counter() - start
        rates[n] = (sum(r.steps for r in results.values()) / elapsed, elapsed)
    raw_rate = raw_steps / raw_time
    images = f"two {image_size}x{image_size} cameras" if cameras else "no cameras"
    print(f"evaluation on mw-quick's 9 tasks x {episodes} episodes, <= {max_steps} steps, {images} "
          f"(untrained default policy on {policy_device_name(policy)}, so episodes run long)")
    print("| what | processes | layout | env steps/s | wall s |")
    print("|---|---|---|---|---|")
    raw_what = "raw simulator + render + scripted experts" if cameras else \
        "raw simulator + scripted experts"
    print(f"| {raw_what} | {workers} | - | {raw_rate:,.0f} | {raw_time:.1f} |")
    for n, (rate, elapsed) in rates.items():
        print(f"| policy evaluation | {n} | {layouts[n]} | {rate:,.0f} | {elapsed:.1f} |")
    print(f"evaluation / raw with {workers} processes: {rates[workers][0] / raw_rate:.2f} (target >= 0.8)")
    print(f"speed-up 1 -> {workers} workers: {rates[1][1] / rates[workers][1]:.2f}x (target >= 1.6x)")


def resolve_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        return torch.device(name)
    except RuntimeError:
        raise ValueError(f"unknown device {name!r}; valid: cpu, cuda, cuda:<i>, auto") from None


def policy_device_name(policy) -> str:
    return str(next(policy.parameters()).device)


def _eval_args(argv: list[str]):
    import argparse

    parser = argparse.ArgumentParser(prog="python -m harness.perf eval")
    parser.add_argument("workers", nargs="?", type=int, default=2)
    parser.add_argument("--cameras", action="store_true", help="render and feed both cameras")
    parser.add_argument("--image-size", type=int, default=128)
    parser.add_argument("--episodes", type=int, default=10, help="per task")
    parser.add_argument("--max-steps", type=int, default=200)
    parser.add_argument("--device", default="cpu", help="cpu, cuda or auto")
    parser.add_argument("--layout", choices=("auto", "per-worker", "central"), default="auto",
                        help="with workers: per-worker policies or one central policy "
                             "(auto: central for a policy on an accelerator)")
    return parser.parse_args(argv)


def main(argv: list[str]) -> int:
    os.environ.setdefault("MUJOCO_GL", "egl")
    torch.set_num_threads(1)
    what = argv[0] if argv else ""
    if what == "train":
        bench_train()
    elif what == "methods":
        bench_methods()
    elif what == "eval":
        args = _eval_args(argv[1:])
        central = {"auto": None, "per-worker": False, "central": True}[args.layout]
        bench_eval(args.workers, args.episodes, args.max_steps, args.cameras, args.image_size,
                   args.device, central)
    elif what == "_memory":
        print(json.dumps(_method_memory(argv[1], steps=30)))
    else:
        print("usage: python -m harness.perf {train,methods,eval [workers] [--cameras] "
              "[--image-size N] [--episodes N] [--max-steps N] [--device D] [--layout L]}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
