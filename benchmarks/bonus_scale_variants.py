"""Variants of the preference-bonus scale on DoorKey-5x5 (tuning seed 100, evaluation seeds 20_000+):
"bonusstd" divides the bonus by the running std of the bonus itself instead of sigma(R_p); "beta03" sets beta 0.3.

    python benchmarks/bonus_scale_variants.py bonusstd 60000
    python benchmarks/bonus_scale_variants.py beta03 60000
"""
import sys, json, gymnasium as gym, numpy as np, torch as th
th.set_num_threads(1)
sys.path.insert(0, str(__import__("pathlib").Path(__file__).parent))
from doorkey import evaluate
from sb3_hhp import HhP
from sb3_hhp.goals import wrap_env
variant, steps = sys.argv[1], int(sys.argv[2])

from bonus_scale_nstep import BonusStd  # sigma = running std of the per-step bonus itself

kw = dict(n_opt=32)
if variant == "beta03": kw["beta"] = 0.3
m = HhP("MlpPolicy", gym.make("MiniGrid-DoorKey-5x5-v0"), oracle="scripted", query_budget=100, seed=100, query_horizon=steps, n_masks=100, **kw)
if variant == "bonusstd": m.return_normalizer = BonusStd()
env = wrap_env(gym.make("MiniGrid-DoorKey-5x5-v0"))
out = []
for chunk in range(4):
    m.learn(steps // 4, reset_num_timesteps=(chunk == 0))
    d = evaluate(m, env, 50, True, 20000); s = evaluate(m, env, 50, True, 20000, deterministic=False)
    out.append(dict(t=m.num_timesteps, det=d["success_rate"], stoch=s["success_rate"], sigma=m.return_normalizer.sigma))
    print(variant, out[-1], flush=True)
