"""Batched evaluation: simulators in worker processes and one central policy give the same
per-episode outcomes as the in-process rollout, chunk-aligned starts change nothing but the
number of policy calls, and on the CPU the outcomes do not depend on the number of workers."""

from dataclasses import dataclass, replace
from types import SimpleNamespace

import pytest
import torch

from harness.evaluate.rollouts import (
    EnvCache,
    EvalSettings,
    Evaluator,
    evaluation_episodes,
    group_by_task,
    rollout,
)
from policies import FlowMatchingConfig, FlowMatchingPolicy
from suites import get_suite

TASKS = ["reach-v3", "push-v3"]
SETTINGS = EvalSettings(episodes=4, max_episode_steps=32, n_action_steps=4, envs_per_task=2)


class ReachController(torch.nn.Module):
    """A policy under the flow-matching contract that needs no training: a proportional controller
    from the hand to the goal (Meta-World's state: hand at 0:3, goal at 36:39), plus a little of
    each episode's sampling noise. Reach episodes succeed after different numbers of steps, so
    slots fall out of step with each other, as a trained policy's do."""

    def __init__(self, chunk_size: int = 4):
        super().__init__()
        self.config = SimpleNamespace(chunk_size=chunk_size, action_dim=4)
        self.gain = torch.nn.Parameter(torch.tensor(10.0))
        self.calls = 0

    def sample_actions(self, batch, noise):
        self.calls += 1
        state = batch["state"]
        move = (self.gain * (state[:, 36:39] - state[:, :3])).clamp(-1, 1)
        action = torch.cat([move, torch.zeros(len(state), 1)], dim=1)
        return action[:, None].expand(-1, self.config.chunk_size, -1) + 0.05 * noise


def _instructions():
    return {t: torch.zeros(384).numpy() for t in TASKS}


def _in_process(policy, settings, align_chunks):
    suite = get_suite("metaworld")
    episodes = evaluation_episodes(suite, TASKS, settings.episodes, settings.max_episode_steps)
    envs = EnvCache(suite, settings)
    try:
        outcomes = rollout(policy, episodes, _instructions(), settings, 5, envs, align_chunks)
    finally:
        envs.close()
    return group_by_task(episodes, outcomes)


def test_chunk_aligned_starts_change_only_the_number_of_policy_calls():
    policy = ReachController()
    plain = _in_process(policy, SETTINGS, align_chunks=False)
    plain_calls, policy.calls = policy.calls, 0
    aligned = _in_process(policy, SETTINGS, align_chunks=True)
    assert aligned == plain
    assert sum(plain["reach-v3"].successes) >= 3 and not any(plain["push-v3"].successes)
    assert plain["reach-v3"].steps % SETTINGS.n_action_steps != 0  # slots did fall out of step
    assert policy.calls < plain_calls


def test_env_workers_with_one_central_policy_match_the_in_process_rollout():
    policy = ReachController()
    # the same slots (4 per task), so the same batches reach the policy: identical outcomes
    expected = _in_process(policy, replace(SETTINGS, envs_per_task=4), align_chunks=True)
    with Evaluator(get_suite("metaworld"), SETTINGS, workers=2, central_policy=True) as evaluator:
        assert evaluator.layout(policy) == "central"
        first = evaluator.evaluate(policy, TASKS, _instructions(), noise_seed=5)
        again = evaluator.evaluate(policy, TASKS, _instructions(), noise_seed=5)  # kept simulators
    assert first == expected and again == expected
    assert {t: len(r.successes) for t, r in first.items()} == {"reach-v3": 4, "push-v3": 4}


def test_the_layout_follows_the_policy_device():
    policy = FlowMatchingPolicy(FlowMatchingConfig(39, 4, size="tiny"))
    suite = get_suite("metaworld")
    assert Evaluator(suite, SETTINGS, workers=1).layout(policy) == "in-process"
    assert Evaluator(suite, SETTINGS, workers=2).layout(policy) == "per-worker"  # CPU: as before
    assert Evaluator(suite, SETTINGS, workers=2).layout(policy.to("meta")) == "central"


def test_a_worker_error_is_raised_in_the_evaluator_naming_its_cause():
    with Evaluator(get_suite("metaworld"), SETTINGS, workers=2, central_policy=True) as evaluator:
        with pytest.raises(RuntimeError, match="unknown metaworld task 'no-such-task'"):
            evaluator.evaluate(ReachController(), ["no-such-task"], {"no-such-task": None}, 0)


@dataclass(frozen=True)
class BatchSizeReachConfig:
    chunk_size: int = 4
    action_dim: int = 4


class BatchSizeReach(ReachController):
    """A reach controller whose gain depends on how many episodes share its call: an exaggerated
    stand-in for a matrix product whose last bits depend on the batch's size. Its outcomes are
    the same in two evaluations only if every call saw the same batch."""

    Config = BatchSizeReachConfig

    def __init__(self, config: BatchSizeReachConfig | None = None):
        super().__init__()
        self.config = config or BatchSizeReachConfig()

    def sample_actions(self, batch, noise):
        state = batch["state"]
        move = (20.0 / len(state) * (state[:, 36:39] - state[:, :3])).clamp(-1, 1)
        action = torch.cat([move, torch.zeros(len(state), 1)], dim=1)
        return action[:, None].expand(-1, self.config.chunk_size, -1) + 0.05 * noise


@pytest.mark.slow
def test_cpu_outcomes_do_not_depend_on_the_number_of_evaluation_workers():
    """Issue 14's executors give a job 1 or 2 evaluation workers depending on how many jobs share
    the machine; the fixed shards keep every policy call's batch, so the results are identical."""
    settings = replace(SETTINGS, episodes=6, max_episode_steps=60, shards=3)
    suite = get_suite("metaworld")
    outcomes = {}
    for workers in (1, 2, 3):
        with Evaluator(suite, settings, workers=workers) as evaluator:
            outcomes[workers] = evaluator.evaluate(BatchSizeReach(), TASKS, _instructions(), 5)
    assert outcomes[1] == outcomes[2] == outcomes[3]
    assert sum(outcomes[1]["reach-v3"].successes) >= 3
    with Evaluator(suite, replace(settings, shards=1), workers=1) as evaluator:  # other batches:
        other = evaluator.evaluate(BatchSizeReach(), TASKS, _instructions(), 5)  # other outcomes
    assert other["reach-v3"].steps != outcomes[1]["reach-v3"].steps
