"""The final evaluation of ``python -m sb3_hhp.train`` and the run's summary.

The trained policy plays one episode on each of a run of fresh envs, built as the training env is, whose seeds start
at ``seed + 10_000`` (:func:`eval_seeds`): never a training seed. :func:`summarize` joins the evaluation with the
run's queries, sub-goals and speed.
"""

from collections.abc import Sequence
from typing import Any

import numpy as np

#: eval seeds start this far above the training seed (training uses seed .. seed + n_envs - 1)
EVAL_SEED_OFFSET = 10_000
#: vectorized evaluation: at most this many fresh envs at once (one episode each)
EVAL_CHUNK = 50


def eval_seeds(seed: int, n_episodes: int, offset: int = EVAL_SEED_OFFSET) -> list[int]:
    """Seeds of the evaluation episodes: ``seed + offset``, ``seed + offset + 1``, ... (one per episode).

    The training env is seeded with ``seed`` (RL Zoo seeds env ``i`` with ``seed + i``, and HhP runs one), so
    with ``offset`` above the number of training envs no evaluation seed is a training seed.

    :param seed: the training seed (>= 0)
    :param n_episodes: number of evaluation episodes (>= 0)
    :param offset: distance from the training seed (>= 1)
    """
    if n_episodes < 0:
        raise ValueError(f"n_episodes must be >= 0, got {n_episodes}")
    if offset < 1:
        raise ValueError(f"offset must be >= 1 so that evaluation never reuses the training seed, got {offset}")
    return [int(seed) + offset + index for index in range(n_episodes)]


def evaluate(model: Any, make_envs: Any, seeds: Sequence[int], deterministic: bool = True) -> dict[str, Any]:
    """Run the policy for one episode per seed, each on a fresh env.

    :param model: a trained HhP
    :param make_envs: ``make_envs(n)`` builds a VecEnv of ``n`` fresh envs wrapped like the training env
        (RL Zoo's ``ExperimentManager.create_envs(n, eval_env=True)``)
    :param seeds: one seed per episode; a chunk of consecutive seeds goes to ``VecEnv.seed(first)``
    :param deterministic: greedy sub-goal choices and primitive actions (else sampled, as in training)
    :return: returns, lengths and successes (``is_success`` when the env reports it, else return > 0)
    """
    from stable_baselines3.common.evaluation import evaluate_policy

    returns: list[float] = []
    lengths: list[int] = []
    successes: list[bool] = []
    seeds = [int(seed) for seed in seeds]
    for start in range(0, len(seeds), EVAL_CHUNK):
        chunk = seeds[start : start + EVAL_CHUNK]
        if chunk != list(range(chunk[0], chunk[0] + len(chunk))):
            raise ValueError("evaluate needs consecutive seeds (VecEnv.seed(s) seeds env i with s + i)")
        env = make_envs(len(chunk))
        reported: dict[int, bool] = {}

        def record(locals_: dict[str, Any], _globals: dict[str, Any]) -> None:
            if locals_["done"] and "is_success" in locals_["info"]:
                reported[int(locals_["i"])] = bool(locals_["info"]["is_success"])

        env.seed(chunk[0])
        try:
            episode_returns, episode_lengths = evaluate_policy(
                model, env, n_eval_episodes=len(chunk), deterministic=deterministic, return_episode_rewards=True,
                callback=record, warn=False,
            )
        finally:
            env.close()
        returns += [float(value) for value in episode_returns]
        lengths += [int(value) for value in episode_lengths]
        successes += [reported.get(index, value > 0) for index, value in enumerate(episode_returns)]
    return {"returns": returns, "lengths": lengths, "successes": successes}


def summarize(
    model: Any, env_id: str, seed: int, seeds: Sequence[int], results: dict[str, Any], train_seconds: float
) -> dict[str, Any]:
    """The run's summary: evaluation, queries, sub-goals and training speed.

    :param model: the trained HhP
    :param env_id: the task
    :param seed: the training seed
    :param seeds: the evaluation seeds
    :param results: :func:`evaluate`'s output
    :param train_seconds: wall-clock seconds of ``learn`` (callbacks included)
    """
    returns = np.asarray(results["returns"], dtype=float)
    subgoals = [model.goal_space.describe(goal.key) for goal in model.subgoals]
    oracle = model.oracle_spec
    return {
        "env": env_id,
        "seed": int(seed),
        "oracle": oracle if isinstance(oracle, str) or oracle is None else type(oracle).__name__,
        "total_timesteps": int(model.num_timesteps),
        "train_seconds": round(float(train_seconds), 3),
        "fps": round(model.num_timesteps / train_seconds, 1) if train_seconds > 0 else None,
        "eval_episodes": len(returns),
        "eval_seeds": [int(value) for value in seeds],
        "success_rate": float(np.mean(results["successes"])) if len(returns) else None,
        "mean_return": float(returns.mean()) if len(returns) else None,
        "std_return": float(returns.std()) if len(returns) else None,
        "mean_episode_length": float(np.mean(results["lengths"])) if len(returns) else None,
        "queries_used": int(model.query_selector.used),
        "queries_asked": int(model.store.count_asked()),
        "queries_distinct": len(model.asked_signatures),
        "query_budget": int(model.query_selector.budget),
        "num_subgoals": len(subgoals),
        "subgoals": subgoals,
        "preference_db": model.preference_db,
    }
