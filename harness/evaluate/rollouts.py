"""Closed-loop evaluation: roll the policy out on every task's fixed, seeded evaluation episodes.

Episodes run in lockstep, so the policy predicts one batch of action chunks for all episodes
that need a new chunk (across tasks: the instruction is per row). Each episode's sampling noise
comes from its own generator, seeded by the episode. A matrix product's last bits can still
depend on the batch's size, so on the CPU the episodes are split into a fixed number of
interleaved shards (`EvalSettings.shards`, the config's `eval_shards`), each rolled out in its
own lockstep: the batch composition of every policy call then depends on the run's settings
only, never on how many workers (or which executor) ran the shards.

With several worker processes there are two layouts, chosen by where the policy lives:

- per-worker policies (a policy on the CPU): each worker holds simulators and a copy of the
  policy, and rolls out whole shards. The CPU default; with one worker the same shards run one
  after another in this process, with the same results.
- one central policy (a policy on an accelerator): the workers only own simulators (`EnvWorkers`)
  and reset or step them on command, while this process runs the lockstep loop and calls
  `policy.sample_actions` once for every slot that needs a chunk, on the device. New episodes
  start on a chunk boundary (`align_chunks`), so there is one policy call per chunk, not up to one
  per step. Per-episode outcomes are the same as in-process ones up to those last bits (tested
  with the same batch composition on the CPU, where they are identical).
"""

from __future__ import annotations

import os
from collections import Counter, deque
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field
from multiprocessing import get_context

import numpy as np
import torch

from harness.common.device import autocast
from harness.common.progress import Progress
from harness.common.seeding import generator
from harness.data.datasets import TrainingData, instruction_entries
from policies.base import noise_shape
from suites import Observation, StepResult, Suite, get_suite
from suites.render import render_argument


@dataclass(frozen=True)
class EvalSettings:
    episodes: int
    max_episode_steps: int
    n_action_steps: int
    cameras: bool = False
    image_size: int = 84
    render: str = "faithful"  # how the images are drawn (suites/render.py)
    envs_per_task: int = 2  # simulators per task and worker; their episodes run one after another
    shards: int = 2  # interleaved shares of the episodes, each its own lockstep (on the CPU)
    spatial_episodes: int = 0  # per task, of the spatial probe's split (widened initial states)
    check_episodes: int = 0  # per task, of the "check" split: matched-target stopping's own
    step_cap: int = 0  # an episode's steps at most, below its task's limit (0: the limit alone)

    def episodes_of(self, split: str) -> int:
        """Episodes per task of a split: "eval" (the success matrix), "spatial" (the probe) or
        "check" (the episodes `until_success` stops on, never the evaluation's)."""
        counts = {"eval": self.episodes, "spatial": self.spatial_episodes,
                  "check": self.check_episodes}
        if split not in counts:
            raise ValueError(f"unknown evaluation split {split!r}; valid: {', '.join(counts)}")
        return counts[split]


@dataclass(frozen=True)
class EvalEpisode:
    task: str
    seed: int  # the suite's reset key: a seed, for LIBERO the fixed init state's index, or a
    # spatial probe's key (suites.base.SPATIAL_KEYS)
    max_steps: int  # the task's step limit (the suite's own where it has one, e.g. LIBERO's)
    record: bool = False  # keep the simulator's state at every step, for a video (recording.py)


@dataclass(frozen=True)
class TaskEvaluation:
    task: str
    successes: tuple[bool, ...]
    steps: int  # environment steps taken, for throughput figures
    # recorded episodes: reset key -> the simulator's state at reset and after every step (not
    # part of equality: two evaluations are equal when their outcomes are)
    recordings: dict[int, np.ndarray] = field(default_factory=dict, compare=False)

    @property
    def success_rate(self) -> float:
        return float(np.mean(self.successes)) if self.successes else float("nan")


class EnvCache:
    """Simulators kept across stages, at most `envs_per_task` per task: building one can take
    longer than an episode, and one per episode would hold gigabytes (robosuite's ~85 MB each)."""

    def __init__(self, suite: Suite, settings: EvalSettings):
        self.suite, self.settings = suite, settings
        self.envs: dict[str, list] = {}

    def for_task(self, task: str, n: int) -> list:
        pool = self.envs.setdefault(task, [])
        while len(pool) < n:
            pool.append(self.suite.make_env(task, self.settings.cameras, self.settings.image_size,
                                            **render_argument(self.settings.render)))
        return pool[:n]

    def close(self) -> None:
        for pool in self.envs.values():
            for env in pool:
                env.close()
        self.envs.clear()


class LocalSimulators:
    """The slots' simulators, in this process: slot i runs `tasks[i]`, drawn from `envs`."""

    def __init__(self, envs: EnvCache, tasks: list[str]):
        pools = {task: iter(envs.for_task(task, n)) for task, n in Counter(tasks).items()}
        self.envs = [next(pools[task]) for task in tasks]

    def reset(self, items: list[tuple[int, int]]) -> list[Observation]:
        """(slot, seed) -> that slot's first observation."""
        return [self.envs[i].reset(seed) for i, seed in items]

    def step(self, items: list[tuple[int, np.ndarray]]) -> list[StepResult]:
        """(slot, action) -> that slot's step result."""
        return [self.envs[i].step(action) for i, action in items]

    def states(self, items: list[tuple[int, None]]) -> list[np.ndarray]:
        """(slot, None) -> that slot's simulator state now (a recorded episode's)."""
        return [self.envs[i].view_state() for i, _ in items]


@dataclass
class _Slot:
    """One simulator running its task's episodes one after another."""

    index: int
    task: str
    episode: int | None = None  # index into the episode list; None when the slot is done
    t: int = 0
    obs: dict | None = None
    plan: np.ndarray | None = None
    noise: torch.Generator | None = None


def policy_device(policy) -> torch.device:
    param = next(iter(policy.parameters()), None)
    return param.device if param is not None else torch.device("cpu")


@torch.no_grad()
def lockstep(policy, episodes: list[EvalEpisode], instructions: dict[str, np.ndarray],
             settings: EvalSettings, noise_seed: int, open_simulators, slots_per_task: int,
             align_chunks: bool = False, recordings: dict[int, list[np.ndarray]] | None = None,
             episode_done=None) -> list[tuple[bool, int]]:
    """(success, steps) per episode. Slots step in lockstep; every slot that needs a new action
    chunk gets it from one batched policy call; a finished episode's slot starts the next
    episode of its task (at once, or with `align_chunks` at the next step that is a multiple of
    n_action_steps, so that all slots need their chunks at the same steps: one policy call per
    chunk instead of up to one per step, for a policy whose call costs the same at any batch).

    `open_simulators(tasks)` gives the simulators of slots running `tasks` (one per slot), with
    `reset` and `step` over lists of (slot, seed) and (slot, action). `episode_done()` is
    called as each episode ends (progress).

    `recordings` (episode index -> states) receives the simulator's state after the reset and
    after every step of each episode marked `record`, read between steps: the episode is the
    same with or without it, and nothing is read when no episode is marked."""
    policy.eval()
    record = recordings is not None and any(ep.record for ep in episodes)
    device = policy_device(policy)
    n_steps = settings.n_action_steps
    chunk_shape = noise_shape(policy, 1)[1:]
    queues: dict[str, deque[int]] = {}
    for i, ep in enumerate(episodes):
        queues.setdefault(ep.task, deque()).append(i)
    tasks = [task for task, queue in queues.items() for _ in range(min(len(queue), slots_per_task))]
    sims = open_simulators(tasks)
    slots = [_Slot(i, task) for i, task in enumerate(tasks)]
    outcomes: list[tuple[bool, int] | None] = [None] * len(episodes)

    def start_next(waiting: list[_Slot]) -> None:
        for slot in waiting:
            queue = queues[slot.task]
            slot.episode = queue.popleft() if queue else None
        starting = [s for s in waiting if s.episode is not None]
        observations = sims.reset([(s.index, episodes[s.episode].seed) for s in starting])
        for slot, obs in zip(starting, observations):
            ep = episodes[slot.episode]
            slot.t, slot.obs = 0, obs
            slot.noise = generator("eval-noise", noise_seed, ep.task, ep.seed)
        if record:
            _record(sims, starting, episodes, recordings)

    waiting, clock = list(slots), 0  # slots between episodes
    while True:
        running = [s for s in slots if s.episode is not None]
        if waiting and (not align_chunks or not running or clock % n_steps == 0):
            start_next(waiting)
            waiting = []
            running = [s for s in slots if s.episode is not None]
        if not running:
            break
        need = [s for s in running if s.t % n_steps == 0]
        if need:
            batch = {k: torch.as_tensor(np.stack([s.obs[k] for s in need])) for k in need[0].obs}
            batch.update(instruction_entries(instructions, [s.task for s in need]))
            batch = {k: v.to(device) for k, v in batch.items()}
            noise = torch.stack([torch.randn(chunk_shape, generator=s.noise) for s in need])
            with autocast(device):
                chunks = policy.sample_actions(batch, noise=noise.to(device))
            for s, chunk in zip(need, chunks.float().cpu().numpy()):
                s.plan = chunk
        results = sims.step([(s.index, s.plan[s.t % n_steps]) for s in running])
        if record:
            _record(sims, running, episodes, recordings)
        clock += 1
        for s, result in zip(running, results):
            s.t += 1
            s.obs = result.obs
            if result.success or s.t >= episodes[s.episode].max_steps:
                outcomes[s.episode] = (result.success, s.t)
                if episode_done is not None:
                    episode_done()
                s.episode = None
                waiting.append(s)
    return outcomes


def _record(sims, slots: list[_Slot], episodes: list[EvalEpisode], recordings: dict) -> None:
    """Append the state of every slot whose episode is recorded."""
    slots = [s for s in slots if episodes[s.episode].record]
    if slots:
        for s, state in zip(slots, sims.states([(s.index, None) for s in slots])):
            recordings.setdefault(s.episode, []).append(state)


def rollout(policy, episodes: list[EvalEpisode], instructions: dict[str, np.ndarray],
            settings: EvalSettings, noise_seed: int, envs: EnvCache,
            align_chunks: bool = False, recordings: dict | None = None, episode_done=None
            ) -> list[tuple[bool, int]]:
    """(success, steps) per episode, on simulators in this process (`lockstep`)."""
    return lockstep(policy, episodes, instructions, settings, noise_seed,
                    lambda tasks: LocalSimulators(envs, tasks), settings.envs_per_task, align_chunks,
                    recordings, episode_done)


def evaluation_episodes(suite: Suite, tasks: list[str], n: int, max_episode_steps: int,
                        split: str = "eval", step_cap: int = 0, record=frozenset()
                        ) -> list[EvalEpisode]:
    """Every task's `n` episodes of `split`; those whose (task, index) is in `record` marked."""
    def limit(task: str) -> int:
        own = suite.step_limit(task, max_episode_steps)
        return min(own, step_cap) if step_cap else own

    return [EvalEpisode(t, key, limit(t), (t, i) in record) for t in tasks
            for i, key in enumerate(suite.episode_keys(t, split, n))]


def shard(episodes: list[EvalEpisode], n: int) -> list[list[EvalEpisode]]:
    """The episodes in `n` interleaved shares (episode i in share i mod n), empty ones dropped:
    every share holds about 1/n of each task's episodes."""
    return [share for share in (episodes[i::n] for i in range(n)) if share]


def group_by_task(episodes: list[EvalEpisode], outcomes: list[tuple[bool, int]],
                  recordings: dict[EvalEpisode, list] | None = None) -> dict[str, TaskEvaluation]:
    by_task: dict[str, list[tuple[bool, int]]] = {}
    for ep, out in zip(episodes, outcomes):
        by_task.setdefault(ep.task, []).append(out)
    kept = {t: {ep.seed: np.stack(states) for ep, states in (recordings or {}).items()
                if ep.task == t} for t in by_task}
    return {t: TaskEvaluation(t, tuple(s for s, _ in v), sum(n for _, n in v), kept[t])
            for t, v in by_task.items()}


class EnvWorkers:
    """Worker processes that own simulators (an EnvCache each, kept between stages) and only
    reset and step them on command; the policy stays in the calling process."""

    def __init__(self, suite_name: str, settings: EvalSettings, workers: int, torch_threads: int = 1):
        ctx = get_context("spawn")
        self._conns, self._procs = [], []
        for _ in range(workers):
            parent, child = ctx.Pipe()
            proc = ctx.Process(target=_env_worker, args=(child, suite_name, settings, torch_threads),
                               daemon=True)
            proc.start()
            child.close()
            self._conns.append(parent)
            self._procs.append(proc)

    def __len__(self) -> int:
        return len(self._conns)

    def open(self, tasks: list[str]) -> RemoteSimulators:
        return RemoteSimulators(self, tasks)

    def call(self, method: str, per_worker: dict[int, list]) -> dict[int, list]:
        """Send every worker its items, then collect the replies: the workers run in parallel."""
        for w, items in per_worker.items():
            self._conns[w].send((method, items))
        replies = {}
        for w in per_worker:
            try:
                ok, payload = self._conns[w].recv()
            except EOFError:
                self._procs[w].join(timeout=5)
                raise RuntimeError(f"evaluation worker {w} died in {method} "
                                   f"(exit code {self._procs[w].exitcode})") from None
            if not ok:
                raise RuntimeError(f"evaluation worker {w} failed in {method}: {payload}")
            replies[w] = payload
        return replies

    def close(self) -> None:
        for conn in self._conns:
            try:
                conn.send(("close", None))
            except (BrokenPipeError, OSError):
                pass
        for proc in self._procs:
            proc.join(timeout=30)
            if proc.is_alive():
                proc.terminate()
        self._conns, self._procs = [], []


class RemoteSimulators:
    """The slots' simulators, spread over `EnvWorkers` round robin (slot i on worker i % n), so
    every worker holds at most ceil(slots of a task / n) simulators of that task."""

    def __init__(self, workers: EnvWorkers, tasks: list[str]):
        n = len(workers)
        self._workers = workers
        self._where = [(i % n, i // n) for i in range(len(tasks))]  # slot -> (worker, its slot)
        workers.call("open", {w: tasks[w::n] for w in range(n) if tasks[w::n]})

    def reset(self, items: list[tuple[int, int]]) -> list[Observation]:
        return self._scatter("reset", items)

    def step(self, items: list[tuple[int, np.ndarray]]) -> list[StepResult]:
        return self._scatter("step", items)

    def states(self, items: list[tuple[int, None]]) -> list[np.ndarray]:
        return self._scatter("states", items)

    def _scatter(self, method: str, items: list) -> list:
        per_worker: dict[int, list] = {}
        for slot, arg in items:
            w, local = self._where[slot]
            per_worker.setdefault(w, []).append((local, arg))
        replies = {w: iter(r) for w, r in self._workers.call(method, per_worker).items()}
        return [next(replies[self._where[slot][0]]) for slot, _ in items]


class Evaluator:
    """Evaluates a policy on a benchmark's tasks, in this process or with `workers` processes.

    With one worker, everything runs here. With more, simulators live in worker processes,
    started once and kept between stages, in one of two ways (see the module docstring):
    per-worker policies (each worker gets the weights and whole shards of the episodes; the
    default for a policy on the CPU) or one central policy (workers only step simulators;
    the default for a policy on an accelerator). `central_policy` overrides the choice.
    """

    def __init__(self, suite: Suite, settings: EvalSettings, workers: int = 1, torch_threads: int = 1,
                 central_policy: bool | None = None, progress: bool = False):
        self.suite, self.settings, self.workers = suite, settings, max(1, workers)
        self.progress = progress  # episodes done out of the total, as they end
        self.torch_threads, self.central_policy = torch_threads, central_policy
        self._local = EnvCache(suite, settings) if self.workers == 1 else None
        self._pool: ProcessPoolExecutor | None = None
        self._env_workers: EnvWorkers | None = None

    def evaluate(self, policy, tasks: list[str], instructions: dict[str, np.ndarray],
                 noise_seed: int, split: str = "eval", record=frozenset()
                 ) -> dict[str, TaskEvaluation]:
        """Per task, its episodes of `split`: "eval", "spatial" (the spatial probe) or "check";
        the episodes whose (task, index) is in `record` keep their states (`recordings`)."""
        episodes = evaluation_episodes(self.suite, tasks, self.settings.episodes_of(split),
                                       self.settings.max_episode_steps, split,
                                       self.settings.step_cap, record)
        with Progress(len(episodes), f"evaluation ({split}) of {len(tasks)} tasks",
                      unit="episodes", enabled=self.progress) as shown:
            return self._evaluate(policy, episodes, instructions, noise_seed, shown)

    def _evaluate(self, policy, episodes: list[EvalEpisode], instructions, noise_seed: int,
                  shown: Progress) -> dict[str, TaskEvaluation]:
        layout = self.layout(policy)
        on_cpu = policy_device(policy).type == "cpu"
        if layout == "central":
            states: dict[int, list] = {}
            outcomes = self._central_rollout(policy, episodes, instructions, noise_seed, states,
                                             shown)
            return group_by_task(episodes, outcomes, {episodes[i]: v for i, v in states.items()})
        # an accelerator's policy rolls everything out in one batch (its numerics differ anyway)
        shards = shard(episodes, self.settings.shards) if on_cpu else [episodes]
        if layout == "in-process":
            results = [_rollout_recorded(policy, share, instructions, self.settings, noise_seed,
                                         self._local, not on_cpu, shown.update)
                       for share in shards]
        else:
            results = self._per_worker_rollout(policy, shards, instructions, noise_seed, shown)
        outcome = {ep: out for share, (outs, _) in zip(shards, results) for ep, out in zip(share, outs)}
        recorded = {share[i]: v for share, (_, states) in zip(shards, results)
                    for i, v in states.items()}
        return group_by_task(episodes, [outcome[ep] for ep in episodes], recorded)

    def layout(self, policy) -> str:
        """Where `policy` would be rolled out: "in-process", "per-worker" or "central"."""
        if self._local is not None:
            return "in-process"
        central = self.central_policy
        if central is None:
            central = policy_device(policy).type != "cpu"
        return "central" if central else "per-worker"

    def _central_rollout(self, policy, episodes, instructions, noise_seed, recordings,
                         shown: Progress
                         ) -> list[tuple[bool, int]]:
        if self._env_workers is None:
            self._env_workers = EnvWorkers(self.suite.name, self.settings, self.workers,
                                           self.torch_threads)
        return lockstep(policy, episodes, instructions, self.settings, noise_seed,
                        self._env_workers.open, self.settings.envs_per_task * self.workers,
                        align_chunks=True, recordings=recordings, episode_done=shown.update)

    def _per_worker_rollout(self, policy, shards, instructions, noise_seed, shown: Progress
                            ) -> list[tuple[list[tuple[bool, int]], dict]]:
        """Each shard's outcomes and recordings, the shards spread over the worker processes."""
        if self._pool is None:
            workers = min(self.workers, self.settings.shards)  # more would have no shard to run
            self._pool = ProcessPoolExecutor(workers, mp_context=get_context("spawn"),
                                             initializer=_init_worker,
                                             initargs=(self.suite.name, self.settings,
                                                       self.torch_threads))
        # a copy: sending tensors to workers moves their storage to shared memory, and during a
        # learning-curve evaluation the parameters are views into the trainer's flat buffer
        weights = {k: v.detach().clone() for k, v in policy.state_dict().items()}
        futures = [self._pool.submit(_worker_rollout, policy.config, weights, share, instructions,
                                     noise_seed) for share in shards]
        for future in as_completed(futures):  # a shard's episodes count as it comes back
            shown.update(len(shards[futures.index(future)]))
        return [future.result() for future in futures]

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(cancel_futures=True)
        if self._env_workers is not None:
            self._env_workers.close()
        if self._local is not None:
            self._local.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


_WORKER: dict = {}


def _init_worker(suite_name: str, settings: EvalSettings, torch_threads: int) -> None:
    os.environ.setdefault("MUJOCO_GL", "egl")
    torch.set_num_threads(torch_threads)
    _WORKER["envs"] = EnvCache(get_suite(suite_name), settings)
    _WORKER["settings"] = settings


def _worker_rollout(config, weights, episodes, instructions, noise_seed):
    from policies import policy_for_config

    if _WORKER.get("config") != config:
        _WORKER["policy"], _WORKER["config"] = policy_for_config(config), config
    policy = _WORKER["policy"]
    policy.load_state_dict(weights)
    return _rollout_recorded(policy, episodes, instructions, _WORKER["settings"], noise_seed,
                             _WORKER["envs"])


def _rollout_recorded(policy, episodes, instructions, settings, noise_seed, envs,
                      align_chunks: bool = False, episode_done=None
                      ) -> tuple[list[tuple[bool, int]], dict]:
    """`rollout`'s outcomes, and the recorded episodes' states by episode index."""
    states: dict[int, list] = {}
    outcomes = rollout(policy, episodes, instructions, settings, noise_seed, envs, align_chunks,
                       states, episode_done)
    return outcomes, states


def _env_worker(conn, suite_name: str, settings: EvalSettings, torch_threads: int) -> None:
    """An `EnvWorkers` process: open slots, reset and step them, until told to close."""
    _init_worker(suite_name, settings, torch_threads)
    sims = None
    try:
        while True:
            try:
                method, items = conn.recv()
            except EOFError:  # the evaluator's process is gone
                return
            if method == "close":
                return
            try:
                if method == "open":
                    sims, reply = LocalSimulators(_WORKER["envs"], items), None
                else:
                    reply = getattr(sims, method)(items)
                conn.send((True, reply))
            except Exception as exc:  # reported to the evaluator, which raises it there
                conn.send((False, f"{type(exc).__name__}: {exc}"))
    finally:
        _WORKER["envs"].close()  # renderers go before EGL itself is torn down at exit


@torch.no_grad()
def heldout_loss(policy, data: TrainingData, seed: int) -> float:
    """Mean flow-matching loss on held-out demos with fixed noise and time draws.

    The draws depend only on `seed` and the data, so the figure is comparable across methods
    and stages: a cheap, deterministic retention signal.
    """
    policy.eval()
    device = next(policy.parameters()).device
    g = torch.Generator().manual_seed(seed)
    noise = torch.randn(noise_shape(policy, len(data)), generator=g)
    time = policy.sample_time(len(data), g)
    batch = data.batch(torch.arange(len(data)))
    batch["noise"], batch["time"] = noise, time
    with autocast(device):
        return policy({k: v.to(device) for k, v in batch.items()}).mean().item()
