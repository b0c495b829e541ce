"""Evaluation results depend on the episodes only: not on batching, simulator reuse or workers."""

import numpy as np
import torch

from harness.evaluate.rollouts import (
    EnvCache,
    EvalSettings,
    Evaluator,
    evaluation_episodes,
    rollout,
)
from policies import FlowMatchingConfig, FlowMatchingPolicy
from suites import get_suite

TASKS = ["reach-v3", "push-v3"]


def _setup():
    torch.manual_seed(0)
    policy = FlowMatchingPolicy(FlowMatchingConfig(39, 4, size="tiny"))
    instructions = {t: np.random.default_rng(i).standard_normal(384).astype(np.float32)
                    for i, t in enumerate(TASKS)}
    return get_suite("metaworld"), policy, instructions


def test_outcomes_do_not_depend_on_how_many_simulators_run_them():
    suite, policy, instructions = _setup()
    episodes = evaluation_episodes(suite, TASKS, 3, 25)
    out = {}
    for per_task in (1, 3):
        settings = EvalSettings(episodes=3, max_episode_steps=25, n_action_steps=3,
                                envs_per_task=per_task)
        cache = EnvCache(suite, settings)
        out[per_task] = rollout(policy, episodes, instructions, settings, 7, cache)
        assert sum(len(v) for v in cache.envs.values()) == per_task * len(TASKS)
        cache.close()
    assert out[1] == out[3]
    assert all(steps == 25 or success for success, steps in out[1])


def test_two_workers_give_the_same_results_as_one():
    suite, policy, instructions = _setup()
    settings = EvalSettings(episodes=2, max_episode_steps=20, n_action_steps=4)
    results = {}
    for workers in (1, 2):
        with Evaluator(suite, settings, workers=workers) as evaluator:
            results[workers] = evaluator.evaluate(policy, TASKS, instructions, noise_seed=3)
    assert results[1] == results[2]
    assert {t: r.steps for t, r in results[1].items()} == {"reach-v3": 40, "push-v3": 40}


def test_eval_step_cap_shortens_evaluation_below_a_tasks_own_limit():
    """LIBERO's tasks have their own limits (220-520 steps), which max_episode_steps does not
    lower; eval_step_cap does, for evaluation only."""
    from harness.evaluate.rollouts import evaluation_episodes

    suite = get_suite("libero")
    task = "pick_up_the_alphabet_soup_and_place_it_in_the_basket"
    own = evaluation_episodes(suite, [task], 2, 100)
    assert {e.max_steps for e in own} == {suite.step_limit(task, 100)} and own[0].max_steps > 100
    capped = evaluation_episodes(suite, [task], 2, 100, "check", step_cap=15)
    assert [e.max_steps for e in capped] == [15, 15]
    assert [e.seed for e in capped] == [e.seed for e in evaluation_episodes(suite, [task], 2, 100,
                                                                             "check")]
    assert evaluation_episodes(suite, [task], 1, 100, step_cap=10_000)[0].max_steps == own[0].max_steps
