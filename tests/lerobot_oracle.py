"""The oracle of tests/test_lerobot_eval_parity.py: one episode rolled out by lerobot-eval's own
parts (LeRobot's env class in a gymnasium vector env, `preprocess_observation`, the env's
processor, the policy's processors and `select_action`, as lerobot_eval.rollout chains them),
and the same episode through Retain's evaluation (`harness.evaluate.rollouts.rollout` on suite
libero-lerobot / metaworld-lerobot), each side recording what the policy receives and returns.

Two shims let LeRobot 0.6.1's LiberoEnv run on robosuite 1.5 (`robosuite14_names`); they are
for this test only: Retain never uses LeRobot's env classes.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass, field

import numpy as np
import torch

from harness.common.seeding import generator
from harness.evaluate.rollouts import EnvCache, EvalSettings, evaluation_episodes, rollout
from policies.base import noise_shape
from policies.lerobot.modeling import fixed_draws

NOISE_SEED = 5


@dataclass
class Trace:
    """What one side's policy saw and did, step by step."""

    observations: list[dict[str, torch.Tensor]] = field(default_factory=list)  # env-processed
    model_inputs: list[dict[str, torch.Tensor]] = field(default_factory=list)  # at each chunk
    actions: list[np.ndarray] = field(default_factory=list)  # as handed to the env's step
    sim_states: list[np.ndarray] = field(default_factory=list)  # after each step
    successes: list[bool] = field(default_factory=list)


@contextlib.contextmanager
def robosuite14_names():
    """LeRobot 0.6.1's LiberoEnv was written for robosuite 1.4: its reset sets
    `robot.controller.use_delta` and its observation reads `controller.ee_ori_mat`. robosuite
    1.5 keeps the arm's controller in `robot.part_controllers` and names the matrix
    `ref_ori_mat`. Shim 1: `controller` is the arm's part controller (robosuite 1.5's OSC reads
    `input_type`, "delta" in LIBERO's config, so the `use_delta=True` LeRobot writes changes
    nothing: `check_shims` holds that). Shim 2: `ee_ori_mat` is `ref_ori_mat`; it only fills
    LeRobot's `robot_state.eef.mat`, which LiberoProcessorStep drops."""
    from robosuite.controllers.parts.arm.osc import OperationalSpaceController
    from robosuite.robots.robot import Robot

    Robot.controller = property(lambda self: self.part_controllers[self.arms[0]])
    OperationalSpaceController.ee_ori_mat = property(lambda self: self.ref_ori_mat)
    try:
        yield
    finally:
        del Robot.controller, OperationalSpaceController.ee_ori_mat


def check_shims(lerobot_vec) -> None:
    """The shims' effect: the arm is in delta control (what LeRobot's use_delta=True asks) and
    the attribute LeRobot wrote is one robosuite 1.5 never reads."""
    robot = lerobot_vec.envs[0]._env.robots[0]
    arm = robot.part_controllers[robot.arms[0]]
    assert arm.input_type == "delta"
    assert arm.use_delta is True  # written by LeRobot's reset, read by nothing in robosuite 1.5


def lerobot_libero(suite: str, task_index: int, size: int):
    from lerobot.envs.libero import LiberoEnv, _get_suite

    from suites.libero.install import point_libero_at_config

    point_libero_at_config()
    return LiberoEnv(_get_suite(suite), task_index, suite, obs_type="pixels_agent_pos",
                     observation_width=size, observation_height=size, episode_index=0)


def lerobot_metaworld(task: str):
    from lerobot.envs.metaworld import MetaworldEnv

    return MetaworldEnv(task, obs_type="pixels_agent_pos")


def env_processors(env_type: str):
    from lerobot.envs.configs import LiberoEnv, MetaworldEnv

    config = {"libero": LiberoEnv, "metaworld": MetaworldEnv}[env_type]()
    return config.get_env_processors()


def chunk_noises(policy, task: str, key: int):
    """The noise Retain's lockstep gives episode (task, key)'s chunks, one after another."""
    g = generator("eval-noise", NOISE_SEED, task, key)
    shape = noise_shape(policy, 1)[1:]
    while True:
        yield torch.randn(shape, generator=g)[None]


def lerobot_rollout(policy, env, env_type: str, task: str, key: int, seed: int, steps: int,
                    numpy_seed: int | None = None) -> Trace:
    """lerobot_eval.rollout's chain for one env, `steps` steps or to success."""
    import gymnasium as gym
    from lerobot.envs.utils import preprocess_observation
    from lerobot.utils.constants import ACTION

    env_pre, env_post = env_processors(env_type)
    pre, post = policy.processors()
    model = policy.model
    vec = gym.vector.SyncVectorEnv([lambda: env], autoreset_mode=gym.vector.AutoresetMode.NEXT_STEP)
    env._ensure_env()  # built before numpy is seeded, as Retain's env is built before its reset
    if numpy_seed is not None:
        np.random.seed(numpy_seed)  # LIBERO's fixture placement (lerobot-eval leaves it unseeded)
    model.reset()
    obs, _ = vec.reset(seed=[seed])
    if env_type == "libero":
        check_shims(vec)
    noises, trace = chunk_noises(policy, task, key), Trace()
    n = model.config.n_action_steps
    for t in range(steps):
        batch = preprocess_observation(obs)
        batch["task"] = list(vec.call("task_description"))
        batch = env_pre(batch)
        trace.observations.append({k: v.clone() for k, v in batch.items() if torch.is_tensor(v)})
        batch = pre(batch)
        with torch.inference_mode():
            if t % n == 0:
                trace.model_inputs.append(_tensors(batch))
                with fixed_draws(model.model, next(noises), torch.zeros(1)):
                    action = model.select_action(batch)  # its queue is empty: a new chunk
            else:
                action = model.select_action(batch)
        action = env_post({ACTION: post(action)})[ACTION].cpu().numpy()
        trace.actions.append(action[0].copy())
        obs, _, terminated, truncated, info = vec.step(action)
        trace.sim_states.append(sim_state(env))
        trace.successes.append(bool(np.asarray(info["is_success"])[0]))
        if terminated[0] or truncated[0]:
            break
    vec.close()
    return trace


def retain_rollout(policy, suite, task: str, steps: int, size: int) -> Trace:
    """Retain's evaluation of the task's episode 0 (capped at `steps`), recorded."""
    trace = Trace()
    settings = EvalSettings(episodes=1, max_episode_steps=suite.max_episode_steps,
                            n_action_steps=policy.config.n_action_steps, cameras=True,
                            image_size=size, envs_per_task=1, shards=1, step_cap=steps)
    envs = EnvCache(suite, settings)
    env = envs.for_task(task, 1)[0]
    step, reset = env.step, env.reset

    def recording_reset(key):
        obs = reset(key)
        trace.observations.append(processed(obs))
        return obs

    def recording_step(action):
        trace.actions.append(np.array(action, copy=True))
        result = step(action)
        trace.sim_states.append(sim_state(env))
        trace.successes.append(bool(result.success))
        trace.observations.append(processed(result.obs))
        return result

    predict = policy.model.predict_action_chunk

    def recording_predict(batch, **kwargs):
        trace.model_inputs.append(_tensors(batch))
        return predict(batch, **kwargs)

    env.step, env.reset, policy.model.predict_action_chunk = recording_step, recording_reset, recording_predict
    try:
        episodes = evaluation_episodes(suite, [task], 1, suite.max_episode_steps, "eval", steps)
        instructions = {task: {"instruction_id": np.int64(0)}}
        ((success, n),) = rollout(policy, episodes, instructions, settings, NOISE_SEED, envs)
    finally:
        del policy.model.predict_action_chunk
        envs.close()
    trace.observations = trace.observations[:n]  # the observation after the last step is unused
    assert success == trace.successes[-1] and n == len(trace.actions)
    return trace


def processed(obs: dict) -> dict[str, torch.Tensor]:
    """Retain's observation, copied (`compare` turns it into LeRobot's names and floats)."""
    return {k: torch.from_numpy(np.array(v, copy=True)) for k, v in obs.items()}


def compare(policy, ours: Trace, theirs: Trace, min_steps: int) -> None:
    """Every observation the policy receives, every model input and every action equal to the
    bit, the simulators' states too, and the same success at the same step."""
    assert len(ours.actions) == len(theirs.actions), (len(ours.actions), len(theirs.actions))
    assert len(ours.actions) >= min_steps or ours.successes[-1]
    assert len(ours.observations) == len(theirs.observations) == len(ours.actions)
    for t, (mine, lerobot) in enumerate(zip(ours.observations, theirs.observations)):
        for key, feature in policy.features.items():
            value = mine[key]
            if value.dtype == torch.uint8:  # as lerobot's preprocess_observation converts it
                value = value.permute(2, 0, 1).type(torch.float32) / 255
            assert torch.equal(value, lerobot[feature][0]), f"step {t}: {key} != {feature}"
    assert len(ours.model_inputs) == len(theirs.model_inputs)
    for k, (mine, lerobot) in enumerate(zip(ours.model_inputs, theirs.model_inputs)):
        for name in lerobot:
            assert torch.equal(mine[name], lerobot[name]), f"chunk {k}: model input {name}"
    for t, (mine, lerobot) in enumerate(zip(ours.actions, theirs.actions)):
        assert mine.dtype == lerobot.dtype and np.array_equal(mine, lerobot), f"step {t}: action"
    last = len(ours.sim_states) - (1 if theirs.successes[-1] else 0)  # LeRobot's Meta-World
    for t in range(last):  # resets itself at success
        assert np.array_equal(ours.sim_states[t], theirs.sim_states[t]), f"step {t}: sim state"
    assert ours.successes == theirs.successes


def sim_state(env) -> np.ndarray:
    """Either side's MuJoCo qpos, qvel and ctrl (ctrl shows the action the simulator took)."""
    inner = getattr(env, "_env", None) or getattr(env, "env", None)
    data = _mujoco_data(inner if inner is not None else env)
    return np.concatenate([data.qpos, data.qvel, data.ctrl]).copy()


def _mujoco_data(env):
    for path in (("sim", "data", "_data"), ("env", "sim", "data", "_data"), ("data",)):
        obj = env
        try:
            for name in path:
                obj = getattr(obj, name)
        except AttributeError:
            continue
        return obj
    raise AttributeError(f"no MuJoCo data in {type(env).__name__}")


def _tensors(batch: dict) -> dict[str, torch.Tensor]:
    return {k: v.detach().clone() for k, v in batch.items() if torch.is_tensor(v)}
