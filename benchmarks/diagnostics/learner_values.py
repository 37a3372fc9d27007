"""The values of a run's sub-goal learners: the pick-up where it is one action, and the scale of every learner's values.

Loads a trained HhP model and, on fresh layouts of a DoorKey env, puts the agent empty-handed on a free cell next to
the key, facing it: there the pick-up (MiniGrid action 3) reaches "carrying key, facing empty" at once. Printed: how
often that learner's greedy action is the pick-up, its Q-value of the pick-up, the best Q-value of the other actions
it may take, and the gap between them (a gap within the network's error lets it turn away and come back instead).
Then, for every sub-goal's learner, the largest and the median greedy value over those states and the states of 30
random steps from each layout's start: with eq. 5's rewards (+1 at the sub-goal, -1 at a failing end, 0 otherwise)
and no curiosity term a return never passes 1, so values far above it mean the learner's values diverged.

    python benchmarks/diagnostics/learner_values.py RUN/MiniGrid-DoorKey-16x16-v0.zip --env MiniGrid-DoorKey-16x16-v0 \\
        --out benchmarks/results/diagnostics/doorkey16x16_s100/learner_values_eval_seed0.json
"""

import argparse
import json
import pathlib
import sys

import gymnasium as gym
import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[2]))
from benchmarks.diagnostics.key_skills import HEADINGS, key_cell  # noqa: E402
from sb3_hhp import HhP  # noqa: E402
from sb3_hhp.goals import wrap_env  # noqa: E402

PICKUP = 3  # MiniGrid's Actions.pickup
GOAL = "carrying key, facing empty"


def facing_key(env: gym.Env, seed: int) -> list[np.ndarray]:
    """Observations of a fresh layout with the agent empty-handed on each free cell next to the key, facing it."""
    env.reset(seed=seed)
    base = env.unwrapped
    key = key_cell(base)
    states = []
    for heading, (dx, dy) in enumerate(HEADINGS):
        cell = (key[0] - dx, key[1] - dy)  # facing `heading` from here looks at the key
        if base.grid.get(*cell) is None:
            base.agent_pos, base.agent_dir = np.array(cell), heading
            states.append(env.observation(base.gen_obs()))
    return states


def random_play(env: gym.Env, seed: int, steps: int = 30) -> list[np.ndarray]:
    """The observations of ``steps`` random actions from a fresh layout's start."""
    obs, _ = env.reset(seed=seed)
    rng, states = np.random.default_rng(seed), [obs]
    for _ in range(steps):
        obs, *_ = env.step(int(rng.integers(env.action_space.n)))
        states.append(obs)
    return states


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("model")
    parser.add_argument("--env", default="MiniGrid-DoorKey-16x16-v0")
    parser.add_argument("--layouts", type=int, default=40)
    parser.add_argument("--first-seed", type=int, default=50_000, help="fresh layouts from this seed on")
    parser.add_argument("--out", default=None)
    args = parser.parse_args()
    model = HhP.load(args.model)
    names = [model.goal_space.describe(goal.key) for goal in model.subgoals]
    if GOAL not in names:
        raise SystemExit(f"the model has no sub-goal {GOAL!r} (its sub-goals: {names})")
    goal = names.index(GOAL)
    env = wrap_env(gym.make(args.env))
    states = [obs for seed in range(args.first_seed, args.first_seed + args.layouts) for obs in facing_key(env, seed)]
    obs = np.stack(states)
    learners = model.subpolicies
    q = learners.q_values(np.full(len(obs), goal), obs).cpu().numpy().astype(float)
    mask = learners.allowed_actions(obs)
    allowed = np.where(mask, q, -np.inf) if mask is not None else q
    greedy = allowed.argmax(axis=1)  # the learner's greedy action, as its act(deterministic=True) takes it
    others = allowed.copy()
    others[:, PICKUP] = -np.inf
    gap = q[:, PICKUP] - others.max(axis=1)
    result = dict(model=args.model, env=args.env, subgoal=GOAL, states=len(obs), layouts=args.layouts,
                  greedy_pickup=float(np.mean(greedy == PICKUP)), q_pickup_mean=float(q[:, PICKUP].mean()),
                  q_best_other_mean=float(others.max(axis=1).mean()), gap_mean=float(gap.mean()),
                  gap_quantiles=dict(zip(["10%", "50%", "90%"], np.quantile(gap, [0.1, 0.5, 0.9]).round(4).tolist())),
                  greedy_actions=np.bincount(greedy, minlength=q.shape[1]).tolist())
    probes = np.concatenate([obs, np.stack([o for seed in range(args.first_seed, args.first_seed + args.layouts)
                                            for o in random_play(env, seed)])])
    scale = {}
    for g, name in enumerate(names):
        values = learners.q_values(np.full(len(probes), g), probes).cpu().numpy().astype(float).max(axis=1)
        scale[name] = dict(max=round(float(values.max()), 3), median=round(float(np.median(values)), 3),
                           updates=int(learners.n_updates[g]))
    result.update(learner_value_scale=scale, gamma=learners.gamma, command=" ".join(sys.argv))
    print(json.dumps(result, indent=2))
    if args.out:
        pathlib.Path(args.out).write_text(json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()
