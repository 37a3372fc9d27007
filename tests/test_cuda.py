"""HhP on a CUDA device: every network (meta-controller, sub-goal learners, RND, preference predictor) lives on the
device and trains there, with each kind of sub-goal learner and with CnnPolicy; a model trained on the GPU saves and
loads onto the CPU and acts there as it did on the GPU. Skipped where no CUDA device is present (CI runs on CPUs);
run on a machine with one: ``python -m pytest tests/test_cuda.py``."""

import os
from typing import Any

import gymnasium as gym
import minigrid  # noqa: F401  (registers the MiniGrid envs)
import numpy as np
import pytest
import torch as th
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.evaluation import evaluate_policy

from sb3_hhp import HhP
from sb3_hhp.goals import wrap_env

#: the device under test; ``SB3_HHP_TEST_DEVICE=cpu`` runs these checks on the CPU (to check the checks themselves)
DEVICE = os.environ.get("SB3_HHP_TEST_DEVICE", "cuda")
pytestmark = pytest.mark.skipif(DEVICE == "cuda" and not th.cuda.is_available(), reason="needs a CUDA device")

DOORKEY = "MiniGrid-DoorKey-5x5-v0"
SMALL: dict[str, Any] = dict(
    buffer_size=2_000, learning_starts=300, batch_size=32, max_subgoal_steps=30, meta_kwargs=dict(target_update_interval=50),
    policy_kwargs=dict(net_arch=[64]), predictor_kwargs=dict(hidden_dim=64, batch_size=32, n_masks=20),
    rnd_kwargs=dict(hidden_dim=64, refresh_interval=500), query_budget=10,
    subpolicy_kwargs=dict(learning_starts=50, buffer_size=2_000, batch_size=32, policy_kwargs=dict(net_arch=[64, 64])),
)
#: the stacked learners as the ``minigrid`` entry of sb3_hhp/hyperparams/hhp.yml runs them (grouped rounds, the inner view)
ENTRY_LEARNERS = dict(train_shared=True, max_updates=6, exploration_steps=500, grouped_rounds=True, view="inner")
#: ... reading the cells as indicators, as the KeyCorridorS4R3 entry's learners do (walls, doors, keys, balls; closed,
#: locked)
ONE_HOT_LEARNERS = dict(ENTRY_LEARNERS, one_hot=[[2, 4, 5, 6], [], [1, 2]])


def tensors(model: HhP) -> dict[str, list[th.Tensor]]:
    """Every parameter and buffer of an HhP model's networks, by owner: the meta-controller, the preference predictor,
    RND, and the sub-goal learners (their modules, or the stacked learners' parameter tensors)."""
    owners: dict[str, Any] = {"meta-controller": model.policy, "predictor": model.predictor.network}
    if model.rnd is not None:
        owners.update({"rnd": model.rnd.predictor, "rnd target": model.rnd.target})
    for name, value in vars(model.subpolicies).items():
        if isinstance(value, (th.nn.Module, th.Tensor)):
            owners[f"learners.{name}"] = value
    return {name: [owner] if isinstance(owner, th.Tensor) else [*owner.parameters(), *owner.buffers()]
            for name, owner in owners.items()}


def devices(model: HhP) -> set[str]:
    return {tensor.device.type for found in tensors(model).values() for tensor in found}


def moved(before: dict[str, list[th.Tensor]], after: dict[str, list[th.Tensor]]) -> set[str]:
    """The owners some tensor of which changed shape or value between two readings of :func:`tensors`."""
    return {name for name, found in after.items()
            if any(old.shape != new.shape or not th.equal(old, new) for old, new in zip(before.get(name, []), found))
            or len(found) != len(before.get(name, []))}


@pytest.mark.parametrize("learner, learner_kwargs",
                         [("stacked", ENTRY_LEARNERS), ("stacked", ONE_HOT_LEARNERS), ("heads", {})],
                         ids=["stacked", "stacked-one-hot", "heads"])
def test_hhp_trains_on_cuda_and_acts_the_same_on_the_cpu(tmp_path, learner: str, learner_kwargs: dict) -> None:
    env = make_vec_env(DOORKEY, n_envs=4, wrapper_class=wrap_env, seed=0)
    model = HhP("MlpPolicy", env, device=DEVICE, seed=0,
                subgoal_learner_kwargs={**(learner_kwargs), 'kind': learner}, **SMALL)
    assert model.device.type == DEVICE
    assert (model.subpolicies._one_hot is not None) == ("one_hot" in learner_kwargs)  # the cells read as indicators
    before = {name: [tensor.detach().clone() for tensor in found] for name, found in tensors(model).items()}
    model.learn(4_000)
    assert len(model.subgoals) >= 2 and model.query_selector.used >= 1
    assert devices(model) == {DEVICE}
    assert {tensor.device.type for tensor in model.subpolicies.policy(0).parameters()} == {DEVICE}  # as SB3 would hold it
    trained = moved(before, tensors(model))
    assert {"meta-controller", "predictor", "rnd"} <= trained
    assert any(name.startswith("learners.") for name in trained), "no sub-goal learner's parameters moved"

    model.save(tmp_path / "model")
    on_cpu = HhP.load(tmp_path / "model", device="cpu")
    assert on_cpu.device.type == "cpu" and devices(on_cpu) == {"cpu"}
    obs = env.reset()
    for _ in range(20):
        gpu_actions, gpu_state = model.predict(obs, deterministic=True)
        cpu_actions, cpu_state = on_cpu.predict(obs, deterministic=True)
        np.testing.assert_array_equal(gpu_actions, cpu_actions)
        obs, _, _, _ = env.step(gpu_actions)
    mean_return, _ = evaluate_policy(on_cpu, make_vec_env(DOORKEY, n_envs=2, wrapper_class=wrap_env, seed=1), n_eval_episodes=4,
                                     warn=False)
    assert np.isfinite(mean_return)


def test_cnn_policy_trains_on_cuda() -> None:
    model = HhP("CnnPolicy", gym.make(DOORKEY), device=DEVICE, seed=0, **{**SMALL, "query_budget": 5})
    model.learn(1_000)
    assert len(model.subgoals) >= 1
    assert devices(model) == {DEVICE}
    actions, _ = model.predict(model.get_env().reset(), deterministic=True)
    assert actions.shape == (1,)
