"""Diagnosis: meta-controller Q-values, centred preference bonus and sub-goal success at the start of DoorKey-5x5.

    python benchmarks/diagnose_meta.py   (25,000 steps, seed 7, N_opt 32, evaluation seeds 20_000+)
"""
import gymnasium as gym, numpy as np, torch as th
th.set_num_threads(1)
from sb3_hhp import HhP
from sb3_hhp.goals import wrap_env
m = HhP("MlpPolicy", gym.make("MiniGrid-DoorKey-5x5-v0"), oracle="scripted", query_budget=100, seed=7, query_horizon=60000, n_masks=100, n_opt=32)
m.learn(25000)
env = wrap_env(gym.make("MiniGrid-DoorKey-5x5-v0"))
names = [m.goal_space.describe(g.key) for g in m.subgoals]
print("labels", len(m.predictor), "acc", m.last_predictor_stats, "sigma", m.return_normalizer.sigma)
from collections import Counter
lab = Counter(a.label.name for _, q, a in m.store.answers_since(0)); print(lab)
for seed in [20000, 20001]:
    obs, _ = env.reset(seed=seed)
    with th.no_grad():
        q = m.q_net(m.policy.obs_to_tensor(obs)[0]).cpu().numpy()[0][:len(names)]
    b = m.preference_bonus(np.repeat(obs[None], len(names), 0), np.arange(len(names)))
    for i in np.argsort(-q)[:6]:
        print(f"  q={q[i]:+.3f} b={b[i]:+.3f} succ={m.subpolicies.success_rate(i)} n={m.subpolicies.attempts[i]} {names[i]}")
    print("  best bonus:", names[int(np.argmax(b))])
import sys
sys.path.insert(0, str(__import__("pathlib").Path(__file__).parent))
from doorkey import evaluate
print("det", evaluate(m, env, 50, True, 20000), "stoch", evaluate(m, env, 50, True, 20000, deterministic=False))
