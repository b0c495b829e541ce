"""Speed and memory figures (`make bench-train`, `make bench-methods`, `make bench-eval`,
`make bench-envs`).

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
from contextlib import contextmanager
from dataclasses import dataclass, field
from multiprocessing import get_context

import torch

from harness.common.device import autocast, resolve_device
from harness.common.errors import RetainError
from harness.config.benchmark import coerce, load_benchmark, parse_overrides
from harness.data.datasets import TrainingData
from harness.evaluate.rollouts import EnvCache, EvalSettings, Evaluator, evaluation_episodes
from harness.train.trainer import PhaseTimer, TrainSettings, train_stage
from methods import TaskContext, get_method, method_names
from policies import make_config, policy_for_config
from policies.text_encoder import tokenize_instructions
from suites.base import CAMERA_KEYS, run_expert_episode

STATE_DIM, ACTION_DIM = 39, 4  # Meta-World's
CAMERAS = ("agentview_rgb", "eye_in_hand_rgb")
# dense bf16 tensor-core peaks, TFLOP/s, by a substring of torch.cuda.get_device_name()
PEAK_BF16_TFLOPS = {"H100 PCIe": 756.0, "H100": 989.0, "H200": 989.0, "H800": 989.0,
                    "A100": 312.0, "L40S": 362.0, "L4": 121.0, "A10": 125.0}


def synthetic_data(n: int, seed: int, task: str = "task", chunk: int = 4,
                   action_dim: int = ACTION_DIM, image_size: int = 0) -> TrainingData:
    g = torch.Generator().manual_seed(seed)
    obs = {"state": torch.randn(n, STATE_DIM, generator=g)}
    for key in CAMERAS if image_size else ():
        obs[key] = torch.randint(0, 256, (n, image_size, image_size, 3), dtype=torch.uint8,
                                 generator=g)
    tokens = torch.from_numpy(tokenize_instructions([SYNTHETIC_INSTRUCTION]))
    return TrainingData(obs, torch.randn(n, chunk, action_dim, generator=g).clamp(-1, 1),
                        torch.ones(n, chunk, dtype=torch.bool), torch.zeros(n, dtype=torch.long),
                        torch.randn(1, 384, generator=g), [task], tokens, torch.tensor([0]))


SYNTHETIC_INSTRUCTION = "pick up the black bowl and place it on the plate"


def _policy(size: str, policy: str = "mlp", **fields) -> torch.nn.Module:
    torch.manual_seed(0)
    fields = {"state_dim": STATE_DIM, "action_dim": ACTION_DIM, "size": size, **fields}
    return policy_for_config(make_config(policy, **fields))


def _ready_method(name: str, policy, foundation: TrainingData, task: TrainingData):
    method = get_method(name)()
    method.after_task(TaskContext(0, "foundation", foundation, policy, 0.05, 0))
    return method, TaskContext(1, "task", task, policy, 0.05, 0)


def bench_train(steps: int = 200, batch_size: int = 256, device: str = "cpu",
                compile: bool = False) -> None:
    """CPU: the step's phases for the CPU sizes. CUDA: pi0's GPU size, samples/s and MFU."""
    if resolve_device(device).type == "cuda":
        bench_train_gpu(resolve_device(device), compile=compile)
        return
    print(f"training throughput (batch {batch_size}, {torch.get_num_threads()} thread; "
          f"{steps} steps for mlp, {steps // 10} for pi0)")
    print("| policy | parameters | samples/s | step ms | outside forward+backward "
          "| of which clip+AdamW | of which data+loop |")
    print("|---|---|---|---|---|---|---|")
    for name, size in (("mlp", "tiny"), ("mlp", "default"), ("pi0", "tiny"), ("pi0", "default")):
        n_steps = steps if name == "mlp" else max(1, steps // 10)
        policy = _policy(size, name)
        data = synthetic_data(20_000, 0)
        ctx = TaskContext(1, "task", data, policy, 0.05, n_steps)
        g = torch.Generator().manual_seed(0)
        warm = TrainSettings(max(2, n_steps // 10), batch_size, 3e-4)
        train_stage(ctx, get_method("sft")(), warm, g)  # warm-up
        timer = PhaseTimer()
        start = time.perf_counter()
        train_stage(ctx, get_method("sft")(), TrainSettings(n_steps, batch_size, 3e-4), g,
                    timer=timer)
        total = time.perf_counter() - start
        share = {k: v / total for k, v in timer.seconds.items()}
        outside = 1 - share.get("forward", 0) - share.get("backward", 0)
        update = share.get("optimizer", 0)
        n_params = sum(p.numel() for p in policy.parameters())
        print(f"| {name} {size} | {n_params:,} | {n_steps * batch_size / total:,.0f} | "
              f"{1000 * total / n_steps:.1f} | {100 * outside:.1f}% (target < 10%) | "
              f"{100 * update:.1f}% | {100 * (outside - update):.1f}% |")


def _peak_tflops(device: torch.device) -> float | None:
    if os.environ.get("RETAIN_PEAK_TFLOPS"):
        return float(os.environ["RETAIN_PEAK_TFLOPS"])
    name = torch.cuda.get_device_name(device)
    return next((v for k, v in PEAK_BF16_TFLOPS.items() if k in name), None)


def step_flops(policy, batch: dict, device: torch.device) -> int:
    """FLOPs of one training step's forward and backward (matmuls, convolutions, attention),
    counted by torch.utils.flop_counter on the real batch."""
    from torch.utils.flop_counter import FlopCounterMode

    with FlopCounterMode(display=False) as counter, autocast(device):
        policy(batch).mean().backward()
    policy.zero_grad(set_to_none=True)
    return counter.get_total_flops()


@dataclass(frozen=True)
class TrainFigures:
    """One timed training stage of a policy (`measure_training`)."""

    compiled: bool
    parameters: int
    samples_per_s: float
    step_ms: float
    flops_per_step: int  # forward and backward, counted by `step_flops`
    mfu: float | None  # achieved FLOP/s over the device's dense bf16 peak; None off CUDA
    peak_gib: float  # peak GPU memory allocated; 0 off CUDA
    first_loss: float  # the warm-up's first step
    final_loss: float  # the timed stage's last 10% of steps


def pi0_gpu_fields(image_size: int = 224, chunk: int = 50, action_dim: int = 7) -> dict:
    """pi0's GPU setting: two cameras, 50-action chunks of 7-d actions (the anchor's)."""
    return dict(action_dim=action_dim, chunk_size=chunk, n_action_steps=chunk,
                image_keys=CAMERAS, image_size=image_size)


def measure_training(policy, data: TrainingData, device: torch.device, batch_size: int,
                     steps: int, warmup: int = 10, compiled: bool = False,
                     backend: str = "inductor") -> TrainFigures:
    """SFT stages of `policy` on `data` where the policy is (bf16 autocast and the fused AdamW
    on CUDA): `warmup` steps (compilation, allocator), then `steps` timed ones."""
    data = data.to(device)
    policy.state_norm.fit(data.obs["state"])
    policy.action_norm.fit(data.actions.flatten(0, 1))
    flops = step_flops(policy, data.batch(torch.arange(batch_size, device=device)), device)
    if compiled:
        policy.compile(backend=backend)
    ctx = TaskContext(1, "task", data, policy, 0.05, steps)
    g = torch.Generator().manual_seed(0)
    losses: list[float] = []
    train_stage(ctx, get_method("sft")(), TrainSettings(warmup, batch_size, 1e-4), g,
                log=lambda step, m: losses.append(m["train/flow_loss"]))
    cuda = device.type == "cuda"
    if cuda:
        torch.cuda.synchronize(device)
        torch.cuda.reset_peak_memory_stats(device)
    start = time.perf_counter()
    result = train_stage(ctx, get_method("sft")(), TrainSettings(steps, batch_size, 1e-4), g)
    if cuda:
        torch.cuda.synchronize(device)
    total = time.perf_counter() - start
    peak = _peak_tflops(device) if cuda else None
    return TrainFigures(
        compiled=compiled, parameters=sum(p.numel() for p in policy.parameters()),
        samples_per_s=steps * batch_size / total, step_ms=1000 * total / steps,
        flops_per_step=flops, mfu=flops * steps / total / 1e12 / peak if peak else None,
        peak_gib=torch.cuda.max_memory_allocated(device) / 2**30 if cuda else 0.0,
        first_loss=losses[0], final_loss=result.final_loss)


def bench_train_gpu(device: torch.device, batch_size: int = 64, steps: int = 50,
                    compile: bool = False) -> None:
    """pi0's GPU size (ViT-B on two 224x224 cameras, 50-action chunks) in bf16 autocast."""
    data = synthetic_data(1024, 0, chunk=50, action_dim=7, image_size=224)
    peak = _peak_tflops(device)
    print(f"pi0 large training on {torch.cuda.get_device_name(device)} (batch {batch_size}, "
          f"{steps} steps after a warm-up, bf16 autocast, fused AdamW; MFU against "
          f"{peak or '?'} TFLOP/s dense bf16)")
    print("| policy | mode | parameters | samples/s | step ms | TFLOP/step | MFU | peak GiB |")
    print("|---|---|---|---|---|---|---|---|")
    for compiled in (False, True) if compile else (False,):
        policy = _policy("large", "pi0", **pi0_gpu_fields()).to(device)
        f = measure_training(policy, data, device, batch_size, steps, compiled=compiled)
        mfu = f"{100 * f.mfu:.1f}% (target >= 40%)" if f.mfu is not None else "n/a"
        print(f"| pi0 large | {'compiled' if compiled else 'eager'} | {f.parameters:,} | "
              f"{f.samples_per_s:,.0f} | {f.step_ms:.1f} | {f.flops_per_step / 1e12:.2f} | "
              f"{mfu} | {f.peak_gib:.1f} |")


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
    """Step time and memory of every registered method (`method_names()`, so a new method
    appears without a change here), interleaved round by round so machine drift cancels out."""
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
        out = subprocess.run([sys.executable, "-m", "harness.perf.throughput", "_memory", name],
                             capture_output=True, text=True, check=True)
        memory[name] = json.loads(out.stdout.strip().splitlines()[-1])
    sft_time = statistics.median(times["sft"])
    sft_mem = max(memory["sft"]["peak_rss_growth_mb"], 1e-9)
    print(f"methods on the default policy (batch 256; step time: median of {rounds} interleaved "
          f"rounds of {steps} steps; memory: peak resident growth from before the method is built "
          f"to the end of training, in a fresh process each)")
    print("| method | needs | step ms | time vs sft | peak RSS growth MB | memory vs sft "
          "| state held MB |")
    print("|---|---|---|---|---|---|---|")
    for name in names:
        t = statistics.median(times[name])
        m = memory[name]
        print(f"| {name} | {get_method(name).needs()} | {1000 * t:.1f} | {t / sft_time:.3f}x | "
              f"{m['peak_rss_growth_mb']:.1f} | {m['peak_rss_growth_mb'] / sft_mem:.2f}x | "
              f"{m['state_mb']:.2f} |")
    n_params = sum(p.numel() * p.element_size() for p in base.parameters()) / 2**20
    print(f"the policy's parameters: {n_params:.2f} MB (a state of that size is a copy of them)")
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
    return sum(run_expert_episode(envs.for_task(ep.task, 1)[0], ep.seed,
                                  min(max_steps, ep.max_steps)).steps for ep in episodes)


@dataclass
class EvalRun:
    """One timed evaluation pass with `processes` processes."""

    processes: int
    layout: str  # "in-process", "per-worker" or "central" (Evaluator.layout)
    steps_per_s: float
    seconds: float
    results: dict = field(default_factory=dict)  # task -> TaskEvaluation


@dataclass
class EvalFigures:
    """Evaluation throughput against raw expert stepping of the same environments."""

    bench: str
    tasks: list[str]
    episodes: int
    max_steps: int
    cameras: bool
    image_size: int
    device: str
    raw_processes: int
    raw_steps_per_s: float
    raw_seconds: float
    runs: list[EvalRun]
    step_limited_by_suite: bool  # LIBERO: each task at its own limit

    def ratio(self) -> float:
        """Evaluation over raw throughput, both with the most processes."""
        return self.runs[-1].steps_per_s / self.raw_steps_per_s


def measure_eval(workers: int = 2, episodes: int = 10, max_steps: int = 200,
                 cameras: bool = False, image_size: int = 84, device: str = "cpu",
                 central_policy: bool | None = None, bench: str = "mw-quick",
                 processes: tuple[int, ...] | None = None,
                 policy_size: str = "default", n_tasks: int = 0) -> EvalFigures:
    """Evaluation env steps/s of an untrained policy against raw expert stepping (with the same
    rendering when cameras are on), with 1 and `workers` processes (or `processes`), on the
    benchmark's tasks (its first `n_tasks`, when given)."""
    from suites import get_suite

    benchmark = load_benchmark(bench)
    suite = get_suite(benchmark.suite)
    tasks = benchmark.all_tasks()
    tasks = tasks[:n_tasks] if n_tasks > 0 else tasks
    eps = evaluation_episodes(suite, tasks, episodes, max_steps)
    settings = EvalSettings(episodes, max_steps, n_action_steps=4, cameras=cameras,
                            image_size=image_size, envs_per_task=benchmark.eval_envs_per_task,
                            shards=max(workers, benchmark.eval_shards))
    ctx = get_context("spawn")
    render = [cameras] * workers, [image_size] * workers
    suites = [benchmark.suite] * workers
    with ProcessPoolExecutor(workers, mp_context=ctx) as pool:  # warm: imports and env builds
        shares = [eps[i::workers] for i in range(workers)]
        list(pool.map(_raw_expert_share, suites, shares, [1] * workers, *render))
        start = time.perf_counter()
        raw_steps = sum(pool.map(_raw_expert_share, suites, shares, [max_steps] * workers, *render))
        raw_time = time.perf_counter() - start
    image_keys = CAMERA_KEYS if cameras else ()
    policy = _policy(policy_size, image_keys=image_keys, image_size=image_size,
                     state_dim=suite.state_dim, action_dim=suite.action_dim
                     ).to(resolve_device(device))
    instructions = {t: torch.randn(384).numpy() for t in tasks}
    runs = []
    for n in processes or (1, workers):
        with Evaluator(suite, settings, workers=n, central_policy=central_policy) as evaluator:
            layout = evaluator.layout(policy)
            evaluator.evaluate(policy, tasks, instructions, noise_seed=0)  # warm
            start = time.perf_counter()
            results = evaluator.evaluate(policy, tasks, instructions, noise_seed=0)
            elapsed = time.perf_counter() - start
        steps = sum(r.steps for r in results.values())
        runs.append(EvalRun(n, layout, steps / elapsed, elapsed, results))
    return EvalFigures(bench, tasks, episodes, max_steps, cameras, image_size,
                       policy_device_name(policy), workers, raw_steps / raw_time, raw_time, runs,
                       bool(suite.max_steps(tasks[0])))


def bench_eval(workers: int = 2, episodes: int = 10, max_steps: int = 200, cameras: bool = False,
               image_size: int = 84, device: str = "cpu", central_policy: bool | None = None,
               bench: str = "mw-quick") -> None:
    """Evaluation env steps/s against raw expert stepping (with the same rendering: raw
    step-plus-render throughput when cameras are on) on a benchmark's tasks; 1 -> 2 worker
    speed-up. A policy on an accelerator is evaluated with one central policy and simulators in
    the workers. A suite with its own step limits (LIBERO) runs each task at its own."""
    f = measure_eval(workers, episodes, max_steps, cameras, image_size, device, central_policy,
                     bench)
    images = f"two {image_size}x{image_size} cameras" if cameras else "no cameras"
    limit = "each task's own step limit" if f.step_limited_by_suite else f"<= {max_steps} steps"
    print(f"evaluation on {bench}'s {len(f.tasks)} tasks x {episodes} episodes, {limit}, {images} "
          f"(untrained default policy on {f.device}, so episodes run long)")
    print("| what | processes | layout | env steps/s | wall s |")
    print("|---|---|---|---|---|")
    raw_what = "raw simulator + render + scripted experts" if cameras else \
        "raw simulator + scripted experts"
    print(f"| {raw_what} | {workers} | - | {f.raw_steps_per_s:,.0f} | {f.raw_seconds:.1f} |")
    for run in f.runs:
        print(f"| policy evaluation | {run.processes} | {run.layout} | {run.steps_per_s:,.0f} | "
              f"{run.seconds:.1f} |")
    print(f"evaluation / raw with {workers} processes: {f.ratio():.2f} (target >= 0.8)")
    print(f"speed-up 1 -> {workers} workers: {f.runs[0].seconds / f.runs[-1].seconds:.2f}x "
          "(target >= 1.6x)")


def bench_envs(bench: str, n_tasks: int = 0, cameras: bool = False, image_size: int = 128,
               steps: int = 200, camera_steps: int = 20, resets: int = 10) -> None:
    """Resident memory and build time of a benchmark's simulators, one per task as an evaluation
    holds them at once (its lockstep batches every task's episodes), in this process; then, for a
    suite with two step paths (LIBERO), the control step's speed on each against its physics."""
    from suites import get_suite

    benchmark = load_benchmark(bench)
    suite = get_suite(benchmark.suite)
    tasks = benchmark.all_tasks()
    tasks = tasks[:n_tasks] if n_tasks > 0 else tasks
    envs = [suite.make_env(tasks[0], cameras, image_size)]  # the first also pays the imports
    base, start = _rss_mb(), time.perf_counter()
    envs += [suite.make_env(task, cameras, image_size) for task in tasks[1:]]
    seconds, total = time.perf_counter() - start, _rss_mb()
    two_paths = hasattr(envs[0], "fast_step")
    for env in envs:
        env.close()
    more = max(1, len(tasks) - 1)
    images = f"two {image_size}x{image_size} cameras" if cameras else "no cameras"
    print(f"{len(tasks)} of {bench}'s {benchmark.suite} simulators in one process, {images}: "
          f"{total / 1024:.1f} GB resident; {(total - base) / more:.0f} MB and "
          f"{seconds / more:.1f} s to build each after the first", flush=True)
    if two_paths and steps > 0:
        for with_cameras, n in [(False, steps)] + ([(True, camera_steps)] if cameras else []):
            env = suite.make_env(tasks[0], with_cameras, image_size)
            try:
                print_step_speeds(tasks[0], *step_speeds(env, n), with_cameras, image_size, n)
                if not with_cameras:
                    free, sweep = (nudged_drift(env, acts) for acts in
                                   (random_actions(n), sweep_actions(n)))
                    print(f"  controls off by a relative {NUDGE:.0e} at every substep, the joint "
                          f"positions {n} steps later: {free:.1e} apart (these random steps), "
                          f"{sweep:.1e} (a sweep into the table and objects)")
                if not with_cameras and resets > 0:
                    keys = suite.episode_keys(tasks[0], "demo", resets)
                    reload, in_place = (fresh_scene_ms(env, keys, r) for r in (True, False))
                    print(f"  a fresh scene's reset ({len(keys)} demo keys): robosuite's reload "
                          f"{reload:.0f} ms, in place {in_place:.0f} ms")
            finally:
                env.close()


# about how far the same torques computed another exact way (another LAPACK route) are apart
NUDGE = 1e-15


def random_actions(steps: int, seed: int = 0):
    """`step_speeds`' episode: uniform in [-1, 1]^7, mostly in free space."""
    import numpy as np

    return np.random.default_rng(seed).uniform(-1, 1, (steps, 7))


def sweep_actions(steps: int, seed: int = 0):
    """A seeded random walk in [-1, 1]^6 with a gripper that opens and closes: the arm sweeps
    the workspace and runs into the table and objects, where a wrong bit grows fastest."""
    import numpy as np

    rng = np.random.default_rng(seed)
    arm = np.clip(np.cumsum(rng.normal(0, 0.3, (steps, 6)), axis=0), -1, 1)
    grip = np.where(np.arange(steps) // 25 % 2 == 0, -1.0, 1.0)[:, None]
    return np.concatenate([arm, grip], axis=1)


def nudged_drift(env, actions, key: int = 0, nudge: float = NUDGE) -> float:
    """How far robosuite's trajectory under `actions` moves when every substep's controls are
    scaled by 1 + `nudge` before the physics step: the largest gap in joint positions at its end.
    Contacts amplify a last-bit change, so a faster control step has to keep robosuite's bits,
    not just its formula, to keep its trajectories."""
    import numpy as np

    def scale() -> None:
        sim.data.ctrl[:] *= 1 + nudge

    env.fast_step = False
    sim, ends = env.env.sim, []
    for hook in (None, scale):
        env.reset(key)
        with _before_step2(sim, hook):
            for action in actions:
                env.step(action)
        ends.append(np.array(sim.data.qpos))
    return float(np.abs(ends[1] - ends[0]).max())


@contextmanager
def _before_step2(sim, hook):
    """Run `hook()` before each physics step robosuite's path takes (`sim.step2`, after the
    substep's controls are set); no hook, nothing changed."""
    if hook is None:
        yield
        return
    step2 = sim.step2

    def hooked() -> None:
        hook()
        step2()

    sim.step2 = hooked
    try:
        yield
    finally:
        del sim.step2  # the class's method again


def fresh_scene_ms(env, keys: list[int], reload: bool) -> float:
    """CPU milliseconds of a LIBERO fresh scene's `start`, by robosuite's reload or in place
    (the default; the same scene to the bit)."""
    env.reload_fresh_scenes = reload
    env.start(keys[0])  # the first in place compiles the loaded poses once
    start = time.process_time()
    for key in keys:
        env.start(key)
    env.reload_fresh_scenes = False
    return 1000 * (time.process_time() - start) / len(keys)


STEP_PATHS = {"physics": "physics alone (mj_step x {substeps})",
              "robosuite": "robosuite's env.step",
              "fast": "fast path (suites/libero/fast_step.py)"}


def step_speeds(env, steps: int, key: int = 0, seed: int = 0,
                repeats: int = 3) -> tuple[dict[str, float], int]:
    """Control steps per second of one seeded random episode from init state `key`: through
    robosuite's `env.step`, through the fast path, and its physics alone: the same episode's
    per-substep controls replayed with `mj_step` (both paths give it to the bit), with the
    cameras rendered once per control step as the observations render them. Timed in the
    process's CPU time, the best of `repeats` interleaved runs each: a shared machine's load only
    ever slows a run down. Also returns the physics substeps per control step."""
    actions = random_actions(steps, seed)
    controls = _recorded_controls(env, actions, key)
    speeds = dict.fromkeys(STEP_PATHS, 0.0)
    for _ in range(repeats):
        speeds["physics"] = max(speeds["physics"], _replayed(env, controls, steps, key))
        for path, fast in (("robosuite", False), ("fast", True)):
            env.fast_step = fast
            env.reset(key)
            start = time.process_time()
            for action in actions:
                env.step(action)
            speeds[path] = max(speeds[path], steps / (time.process_time() - start))
    return speeds, len(controls) // steps


def _recorded_controls(env, actions, key: int) -> list:
    """Each substep's data.ctrl as robosuite's path sets it before `mj_step2` (not timed)."""
    env.fast_step = False
    env.reset(key)
    sim, controls = env.env.sim, []
    with _before_step2(sim, lambda: controls.append(sim.data.ctrl.copy())):
        for action in actions:
            env.step(action)
    return controls


def _replayed(env, controls: list, steps: int, key: int) -> float:
    import mujoco

    env.fast_step = False
    env.reset(key)
    sim = env.env.sim
    model, data = sim.model._model, sim.data._data
    raw = env.env.env
    cameras = list(zip(raw.camera_names, raw.camera_widths, raw.camera_heights, strict=True))
    cameras = cameras if raw.use_camera_obs else []
    substeps = len(controls) // steps
    start = time.process_time()
    for i, ctrl in enumerate(controls):
        data.ctrl[:] = ctrl
        mujoco.mj_step(model, data)
        if (i + 1) % substeps == 0:
            for camera, width, height in cameras:
                sim.render(width=width, height=height, camera_name=camera)
    return steps / (time.process_time() - start)


def print_step_speeds(task: str, speeds: dict[str, float], substeps: int, cameras: bool,
                      image_size: int, steps: int) -> None:
    images = f"two {image_size}x{image_size} cameras" if cameras else "no cameras"
    render = " + 2 renders" if cameras else ""
    print(f"control step of {task} ({steps} seeded random steps from init state 0), {images}:")
    physics = speeds["physics"]
    for path, label in STEP_PATHS.items():
        label = label.format(substeps=substeps) + (render if path == "physics" else "")
        print(f"  {label:<44} {speeds[path]:7.1f} steps/s  {physics / speeds[path]:5.2f}x "
              f"the physics' time")


def policy_device_name(policy) -> str:
    return str(next(policy.parameters()).device)


def _eval_args(argv: list[str]):
    import argparse

    parser = argparse.ArgumentParser(prog="python -m harness.perf.throughput eval")
    parser.add_argument("workers", nargs="?", type=int, default=2)
    parser.add_argument("--bench", default="mw-quick", help="the benchmark whose tasks to evaluate")
    parser.add_argument("--cameras", action="store_true", help="render and feed both cameras")
    parser.add_argument("--image-size", type=int, default=128)
    parser.add_argument("--episodes", type=int, default=10, help="per task")
    parser.add_argument("--max-steps", type=int, default=200)
    parser.add_argument("--device", default="cpu", help="cpu, cuda or auto")
    parser.add_argument("--layout", choices=("auto", "per-worker", "central"), default="auto",
                        help="with workers: per-worker policies or one central policy "
                             "(auto: central for a policy on an accelerator)")
    return parser.parse_args(argv)


def _envs_args(argv: list[str]):
    import argparse

    parser = argparse.ArgumentParser(prog="python -m harness.perf.throughput envs")
    parser.add_argument("--bench", default="libero-paper", help="the benchmark whose tasks to build")
    parser.add_argument("--tasks", type=int, default=0, help="its first N tasks (0: all)")
    parser.add_argument("--cameras", action="store_true", help="with both cameras' renderers")
    parser.add_argument("--image-size", type=int, default=128)
    parser.add_argument("--steps", type=int, default=200,
                        help="control steps timed per path, no cameras (0: skip the step speeds)")
    parser.add_argument("--camera-steps", type=int, default=20, help="the same, with cameras")
    parser.add_argument("--resets", type=int, default=10,
                        help="fresh-scene resets timed per way, reload and in place (0: skip)")
    parser.add_argument("--view-frames", type=int, default=100,
                        help="frames per suite drawn both ways, render=faithful and render=fast, "
                             "for LIBERO, Meta-World and bimanual (0: skip)")
    return parser.parse_args(argv)


def main(argv: list[str]) -> int:
    os.environ.setdefault("MUJOCO_GL", "egl")
    torch.set_num_threads(1)
    what = argv[0] if argv else ""
    if what == "train":
        settings = parse_overrides(argv[1:])  # make bench-train device=cuda compile=true
        bad = sorted(set(settings) - {"device", "compile"})
        if bad:
            print(f"unknown setting {bad[0]!r} for bench-train; valid: device, compile",
                  file=sys.stderr)
            return 2
        try:
            bench_train(device=settings.get("device", "cpu"),
                        compile=coerce("compile", settings.get("compile", "false"), bool))
        except RetainError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
    elif what == "methods":
        bench_methods()
    elif what == "eval":
        args = _eval_args(argv[1:])
        central = {"auto": None, "per-worker": False, "central": True}[args.layout]
        bench_eval(args.workers, args.episodes, args.max_steps, args.cameras, args.image_size,
                   args.device, central, args.bench)
    elif what == "envs":
        args = _envs_args(argv[1:])
        try:
            bench_envs(args.bench, args.tasks, args.cameras, args.image_size, args.steps,
                       args.camera_steps, args.resets)
            if args.view_frames > 0:
                from harness.perf.views import bench_views

                bench_views(args.view_frames, args.image_size)
        except RetainError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
    elif what == "_memory":
        print(json.dumps(_method_memory(argv[1], steps=30)))
    else:
        print("usage: python -m harness.perf.throughput {train [device=cuda compile=true],methods,eval "
              "[workers] [--cameras] [--image-size N] [--episodes N] [--max-steps N] [--device D] "
              "[--layout L],envs [--bench B] [--tasks N] [--cameras] [--image-size N] [--steps N] "
              "[--camera-steps N]}",
              file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
