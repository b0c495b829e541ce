"""lerobot-eval parity (issue 61): suites libero-lerobot and metaworld-lerobot give a LeRobot
policy what lerobot-eval gives it. The oracle is LeRobot's own env classes and processors
(tests/lerobot_oracle.py): the same tiny policy, task, episode and noise, rolled out both ways,
must see equal observations and return equal actions, step for step, to the bit."""

import numpy as np
import pytest
import torch

from policies import get_policy
from suites import get_suite
from suites.base import AGENTVIEW as AGENT
from suites.base import CAMERA_KEYS

PX = 32  # the policies' own resolution (LeRobot's processors resize whatever the env renders)
LIBERO_PX = 64  # LIBERO's render size in the oracle (lerobot-eval renders 360; costs the same)
STEPS = 50


def build(kind: str, suite, task: str):
    """A tiny LeRobot policy with the suite's LeRobot feature names, fixed weights and wide
    action statistics (so some actions leave [-1, 1] and the env's clipping is exercised)."""
    features = dict(suite.lerobot.features)
    cls = get_policy(kind)
    config = cls.Config(state_dim=suite.state_dim, action_dim=suite.action_dim, size="tiny",
                        chunk_size=6, n_action_steps=4, image_size=PX,
                        image_keys=tuple(k for k in CAMERA_KEYS if k in features),
                        instructions=(suite.instruction(task),),
                        features=tuple(features.items()))
    torch.manual_seed(0)
    policy = cls(config)
    g = torch.Generator().manual_seed(1)
    policy.state_norm.fit(torch.randn(64, suite.state_dim, generator=g) * 0.3)
    policy.action_norm.fit(torch.randn(64, suite.action_dim, generator=g) * 1.5)
    return policy


# ---- the conventions, against LeRobot's own tables (make test) ------------------------------

def lerobot_constant(module: str, name: str):
    """A literal of LeRobot's source (`module` as "envs/libero.py"), read without importing
    it (importing lerobot.envs loads LIBERO's simulator and LeRobot's policies: 10 s and more)."""
    import ast
    import importlib.util
    from pathlib import Path

    root = importlib.util.find_spec("lerobot").submodule_search_locations[0]
    source = (Path(root) / module).read_text()
    for node in ast.parse(source).body:
        target = getattr(node, "target", None) or (getattr(node, "targets", None) or [None])[0]
        if getattr(target, "id", None) == name:
            return ast.literal_eval(node.value)
    raise LookupError(f"{module} has no {name}")


def test_libero_step_limits_are_lerobots_and_openpis_stay_in_suite_libero():
    TASK_SUITE_MAX_STEPS = lerobot_constant("envs/libero.py", "TASK_SUITE_MAX_STEPS")  # noqa: N806
    assert TASK_SUITE_MAX_STEPS["libero_spatial"] == 280

    from suites.libero.lerobot_protocol import LEROBOT_MAX_STEPS
    from suites.libero.tasks import MAX_STEPS, suite_tasks

    assert LEROBOT_MAX_STEPS == TASK_SUITE_MAX_STEPS
    lerobot, libero = get_suite("libero-lerobot"), get_suite("libero")
    for name, limit in TASK_SUITE_MAX_STEPS.items():
        task = suite_tasks(name)[0]
        assert lerobot.max_steps(task) == limit
        assert libero.max_steps(task) == MAX_STEPS[name]
    assert libero.max_steps(suite_tasks("libero_spatial")[0]) == 220  # openpi's, unchanged
    assert lerobot.episode_keys(suite_tasks("libero_goal")[0], "eval", 3) == [0, 1, 2]


def test_metaworld_instructions_seeds_and_limit_are_lerobots():
    from lerobot.configs.eval import EvalPipelineConfig
    from lerobot.envs.metaworld import TASK_DESCRIPTIONS

    suite, retain = get_suite("metaworld-lerobot"), get_suite("metaworld")
    assert len(suite.task_names()) == 50  # LeRobot's texts, even where two tasks share one
    for task in suite.task_names():
        assert suite.instruction(task) == TASK_DESCRIPTIONS[task]
        assert suite.max_steps(task) == 500
    assert retain.instruction("assembly-v3") != suite.instruction("assembly-v3")
    seed = EvalPipelineConfig.__dataclass_fields__["seed"].default  # lerobot-eval's --seed
    assert suite.episode_keys("door-open-v3", "eval", 3) == [seed, seed + 1, seed + 2]


def test_metaworld_lerobots_expert_still_succeeds_on_lerobots_env():
    """The MT1 env LeRobot builds hides the goal from its observation; the suite shows it again
    for the scripted experts (demos), which changes none of LeRobot's four state values."""
    from suites.base import run_expert_episode

    suite = get_suite("metaworld-lerobot")
    env = suite.make_env("door-open-v3")
    try:
        seed = suite.episode_keys("door-open-v3", "eval", 1)[0]
        episode = run_expert_episode(env, seed, suite.max_steps("door-open-v3"), record=True)
        assert episode.success
        assert episode.observations[0]["state"].shape == (4,)
        assert np.any(env._obs[36:39] != 0)  # the goal is visible to the expert
    finally:
        env.close()


def test_the_protocols_image_sizes_are_lerobot_evals():
    from lerobot.envs.configs import LiberoEnv

    assert get_suite("libero-lerobot").lerobot.image_size == LiberoEnv().observation_height
    from lerobot.envs.metaworld import MetaworldEnv

    assert get_suite("metaworld-lerobot").lerobot.image_size == MetaworldEnv("door-open-v3").observation_height


# ---- the oracle (slow: LIBERO renders in software) ------------------------------------------

LIBERO_CASES = [("libero_spatial", 0), ("libero_goal", 1)]
METAWORLD_CASES = ["door-open-v3", "button-press-v3"]
KINDS = ["lerobot_smolvla", "lerobot_pi05"]


def libero_oracle(kind: str, suite_name: str, task_index: int, steps: int = STEPS):
    from suites.libero.tasks import suite_tasks
    from tests import lerobot_oracle as oracle

    suite = get_suite("libero-lerobot")
    task = suite_tasks(suite_name)[task_index]
    policy = build(kind, suite, task)
    with oracle.robosuite14_names():
        env = oracle.lerobot_libero(suite_name, task_index, LIBERO_PX)
        theirs = oracle.lerobot_rollout(policy, env, "libero", task, key=0, seed=1000,
                                        steps=steps, numpy_seed=0)
    ours = oracle.retain_rollout(policy, suite, task, steps, LIBERO_PX)
    return policy, ours, theirs


def metaworld_oracle(kind: str, task: str, steps: int = STEPS):
    from suites.metaworld.lerobot_protocol import LEROBOT_IMAGE_SIZE
    from tests import lerobot_oracle as oracle

    suite = get_suite("metaworld-lerobot")
    policy = build(kind, suite, task)
    key = suite.episode_keys(task, "eval", 1)[0]
    theirs = oracle.lerobot_rollout(policy, oracle.lerobot_metaworld(task), "metaworld", task,
                                    key=key, seed=key, steps=steps)
    ours = oracle.retain_rollout(policy, suite, task, steps, LEROBOT_IMAGE_SIZE)
    return policy, ours, theirs


@pytest.mark.slow
@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("suite_name,task_index", LIBERO_CASES)
def test_libero_episode_is_lerobot_evals(kind, suite_name, task_index):
    from tests.lerobot_oracle import compare

    policy, ours, theirs = libero_oracle(kind, suite_name, task_index)
    compare(policy, ours, theirs, STEPS)
    assert any(np.abs(a).max() > 1 for a in ours.actions)  # clipping was exercised


@pytest.mark.slow
@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("task", METAWORLD_CASES)
def test_metaworld_episode_is_lerobot_evals(kind, task):
    from tests.lerobot_oracle import compare

    policy, ours, theirs = metaworld_oracle(kind, task)
    compare(policy, ours, theirs, STEPS)
    assert any(np.abs(a).max() > 1 for a in ours.actions)


@pytest.mark.slow
@pytest.mark.parametrize("broken", ["no flip", "9 wait steps", "camera corner"])
def test_a_broken_convention_fails_the_oracle(monkeypatch, broken):
    from tests.lerobot_oracle import compare

    if broken == "no flip":
        monkeypatch.setattr("suites.libero.lerobot_protocol.flip_images", lambda obs: obs)
    elif broken == "9 wait steps":
        monkeypatch.setattr("suites.libero.env.SETTLE_STEPS", 9)
    else:
        monkeypatch.setattr("suites.metaworld.lerobot_protocol.LEROBOT_CAMERA", "corner")
    if broken == "camera corner":
        policy, ours, theirs = metaworld_oracle("lerobot_smolvla", METAWORLD_CASES[0], steps=2)
    else:
        policy, ours, theirs = libero_oracle("lerobot_smolvla", *LIBERO_CASES[0], steps=2)
    with pytest.raises(AssertionError, match="step 0"):
        compare(policy, ours, theirs, 2)


@pytest.mark.parametrize("kind", KINDS)
def test_a_chunk_is_executed_as_select_action_queues_it_unnormalized_and_unclipped(kind):
    """Retain's chunk (LeRobot's predict_action_chunk, then the policy's postprocessor) is the
    n_action_steps actions select_action pops one by one through the same postprocessor, to
    the bit, beyond [-1, 1] where the statistics put them: the env gets them as lerobot-eval
    gives them (LIBERO's robosuite and Meta-World clip them themselves; the oracle tests hold
    the simulators' states equal)."""
    from policies.base import noise_shape
    from policies.lerobot.modeling import fixed_draws

    suite = get_suite("metaworld-lerobot")
    policy = build(kind, suite, "door-open-v3")
    g = torch.Generator().manual_seed(3)
    batch = {"state": torch.randn(1, 4, generator=g),
             AGENT: torch.randint(0, 256, (1, PX, PX, 3), dtype=torch.uint8, generator=g),
             "instruction_id": torch.tensor([0])}
    noise = torch.randn(noise_shape(policy, 1), generator=g)
    chunk = policy.sample_actions(batch, noise=noise)[0]
    pre, post = policy.processors()
    model, n = policy.model, policy.config.n_action_steps
    model.reset()
    popped = []
    for t in range(n + 1):
        lr_batch = policy._lerobot_batch(batch, actions=False)
        draws = noise if t == 0 else torch.zeros_like(noise)  # a refill draws anew
        with torch.inference_mode(), fixed_draws(model.model, draws, torch.zeros(1)):
            popped.append(post(model.select_action(lr_batch))[0])
    assert torch.equal(torch.stack(popped[:n]), chunk[:n])
    assert not torch.equal(popped[n], chunk[n])  # the queue was empty: a new chunk
    assert chunk.abs().max() > 1  # unnormalized, not clipped


# ---- a checkpoint under the protocol (make test) ---------------------------------------------

@pytest.fixture(scope="module")
def libero_checkpoint(tmp_path_factory):
    """A tiny SmolVLA with LeRobot's LIBERO features, saved as a LeRobot folder."""
    suite = get_suite("libero-lerobot")
    policy = build("lerobot_smolvla", suite, suite.task_names()[0])
    return policy.save_folder(tmp_path_factory.mktemp("ckpt") / "smolvla_libero")


def plan_settings(folder, suite_name, **settings):
    from harness.config.benchmark import resolve
    from harness.data.lerobot.checkpoint import checkpoint_features, checkpoint_settings, spec

    spec.cache_clear()
    cfg = resolve(["BENCH=libero-paper-lerobot", "PROFILE=tiny", "policy=lerobot_smolvla",
                   f"suite={suite_name}", f"policy_path={folder}",
                   *(f"{k}={v}" for k, v in settings.items())])
    suite = get_suite(cfg.suite)
    return checkpoint_features(cfg, suite), checkpoint_settings(cfg, suite)


def test_lerobots_libero_names_need_no_lerobot_keys_and_render_at_lerobot_evals_size(
        libero_checkpoint):
    import json

    from harness.common.errors import RetainError

    features, settings = plan_settings(libero_checkpoint, "libero-lerobot")
    assert features == {"state": "observation.state", "agentview_rgb": "observation.images.image",
                        "eye_in_hand_rgb": "observation.images.image2"}
    assert settings["image_size"] == 360  # no train_config.json: lerobot-eval's default
    config = {"env": {"type": "libero", "task": "libero_spatial", "observation_height": 256,
                      "observation_width": 256}}
    (libero_checkpoint / "train_config.json").write_text(json.dumps(config))
    try:
        assert plan_settings(libero_checkpoint, "libero-lerobot")[1]["image_size"] == 256
        config["env"]["type"] = "metaworld"
        (libero_checkpoint / "train_config.json").write_text(json.dumps(config))
        with pytest.raises(RetainError, match="trained for LeRobot's 'metaworld' env"):
            plan_settings(libero_checkpoint, "libero-lerobot")
    finally:
        (libero_checkpoint / "train_config.json").unlink()
    with pytest.raises(RetainError, match="lerobot_rotate_images=true with suite 'libero-lerobot'"):
        plan_settings(libero_checkpoint, "libero-lerobot", lerobot_rotate_images="true")
    # Retain's own suite keeps the checkpoint's trained size and its 8-D-state hint
    with pytest.raises(RetainError, match="use suite=libero-proprio"):
        plan_settings(libero_checkpoint, "libero")


# LIBERO renders in software (about 0.1 s a view): the Spatial target's expert demos with two
# cameras and the stage evaluations are minutes
@pytest.mark.slow
def test_libero_paper_lerobot_with_a_lerobot_checkpoint_as_the_base(libero_checkpoint, tmp_path):
    import json

    from harness.run.cli import main

    args = ["bench", "BENCH=libero-paper-lerobot", "PROFILE=tiny", "METHOD=sft",
            "policy=lerobot_smolvla", f"policy_path={libero_checkpoint}",
            f"results_dir={tmp_path}/results", f"cache_dir={tmp_path}/cache", "progress=false",
            "eval_workers=1", "demos_per_task=1", "eval_episodes=1", "check_episodes=1",
            "eval_step_cap=15"]  # no lerobot_keys: the features are LeRobot's LIBERO names
    assert main(args) == 0
    run = next((tmp_path / "results" / "libero-paper-lerobot-tiny").glob("sft*/seed0"))
    config = (run / "config.yaml").read_text()
    assert "suite: libero-lerobot" in config and "image_size: 360" in config
    stages = json.loads((run / "metrics.json").read_text())["stages"]
    assert len(stages) == 2 and np.isnan(stages[0]["train_loss"])  # the base: not retrained


def test_a_saved_smolvla_loads_when_the_policy_that_saved_it_is_gone(libero_checkpoint):
    """A random-init SmolVLA's tokenizer is its scratch VLM folder's, which goes with the policy;
    the folder keeps a copy (vlm/), and loading it must use that one (it did not, until the
    libero-paper-lerobot run with such a checkpoint as its base)."""
    import gc
    import json
    from pathlib import Path

    gc.collect()  # the fixture's policy, and with it its scratch folder
    saved = json.loads((libero_checkpoint / "policy_preprocessor.json").read_text())
    names = [s.get("config", {}).get("tokenizer_name") for s in saved["steps"]]
    assert not any(name and Path(name).is_dir() for name in names)  # gone
    cls = get_policy("lerobot_smolvla")
    suite = get_suite("libero-lerobot")
    features = tuple(dict(suite.lerobot.features).items())
    policy = cls(cls.Config(state_dim=8, action_dim=7, size="tiny", chunk_size=6,
                            n_action_steps=4, image_size=PX, image_keys=CAMERA_KEYS,
                            instructions=("a",), features=features, path=str(libero_checkpoint)))
    assert policy.processors()[0] is not None
