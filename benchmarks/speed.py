"""Speed and memory of HhP with the configuration users train with (the YAML entry of the env).

The measurements, one torch thread each unless ``--threads``:

``ratio``: HhP (the env's ``sb3_hhp/hyperparams/hhp.yml`` entry, with the scripted oracle and a preference file, as
``sb3_hhp.train`` builds it) against flat SB3 DQN doing the same learning work per
primitive step on the same observation (the entry's sub-goal learner: MLP, ``train_freq``, ``batch_size``), both
timed over the same late window of a run (default steps 20,000-30,000, when sub-goals have accumulated), in one
process, the flat DQN once before HhP and once after it over as many steps (HhP is compared with their mean: the
machine drifts); then a profiled continuation of HhP (where the time goes)::

    python benchmarks/speed.py ratio --env MiniGrid-DoorKey-8x8-v0 --out benchmarks/results/speed

``late``: a saved run's model (e.g. the benchmark runner's DoorKey-8x8 run at 300,000 steps) trained on for
``--profile-steps`` more steps, timed, then with a clock around each part of a step (:func:`timed_parts`: its
``shares``), then profiled, against flat SB3 DQN timed as in ``ratio`` over the same number of steps: the speed late
in a run, when sub-goals have accumulated and episodes are short; ``--replay``
(a checkpoint's ``replay.pkl``) fills the learners' replays as the run had them (else they start empty)::

    python benchmarks/speed.py late --model RUN/MiniGrid-DoorKey-8x8-v0.zip --n-envs 8
    python benchmarks/speed.py late --env MiniGrid-KeyCorridorS4R3-v0 --n-envs 8 --model CKPT/model.zip --replay CKPT/replay.pkl

``ab``: two settings of the sub-goal learners (``--learners-a``, ``--learners-b``, JSON attributes, e.g.
``{"grouped_rounds": true}``; ``{"keep_encoded": false}``: the replay keeps no places of one-hot indicators) trained
on, alternately, from one saved state of a run (HhP.save and save_replay_buffer at ``--start`` steps), ``--repeats``
pairs of ``--profile-steps`` steps each::

    python benchmarks/speed.py ab --env MiniGrid-DoorKey-8x8-v0 --n-envs 8 --start 20000 --profile-steps 6000

``subgoals``: HhP with K sub-goals handed in (``discovery="none"``), K = 2 and 32, each in a fresh process, with the
env's YAML entry (its policy and ``env_wrapper``): the cost of a primitive step (after a warm-up), the peak resident
memory and the sub-goal learners' replay::

    python benchmarks/speed.py subgoals --env MiniGrid-DoorKey-8x8-v0 --out benchmarks/results/speed
    python benchmarks/speed.py subgoals --env ALE/MontezumaRevenge-v5 --start 500 --stop 1500

``floor``: what a primitive step cannot cost less than with the entry's learning work: the envs alone (random actions,
the entry's observation wrapper) and one learning round's arithmetic alone (the sub-goal learners' batched matrix
products at ``max_updates`` learners: the online forward pass over ``s`` and the closing states, the target's over
the closing states, the written-out backward pass; then with the Adam step), each timed on its own; the steps per
second a run could not exceed even if nothing else cost anything::

    python benchmarks/speed.py floor --env MiniGrid-DoorKey-8x8-v0 --n-envs 8

``parts``: where a step's time goes against the flat DQN, from one saved state of a run (as ``ab``): ``--repeats``
alternating pairs of ``--profile-steps`` steps, HhP as it is (the time inside the sub-goal learners' grouped updates
counted apart) and HhP with those updates left out (everything else a step costs); the flat DQN timed as in ``ratio``::

    python benchmarks/speed.py parts --env MiniGrid-DoorKey-8x8-v0 --n-envs 8 --seed 2 --start 25000 --profile-steps 5000

``entry``: HhP as the env's YAML entry trains it, whatever the env (its policy, observation wrapper and number of
envs: Atari's CnnPolicy on 84x84 frames too), timed over a window; ``--hhp-kwargs`` sets e.g. the device::

    python benchmarks/speed.py entry --env ALE/Pong-v5 --start 1000 --stop 2000 --hhp-kwargs '{"device": "cuda"}'

with ``--vs-dqn``, against SB3's DQN on the same envs (the entry's policy, ``env_wrapper`` and number of envs; SB3's
``train_freq`` 4 and batch 32: one update per 4 primitive steps), timed over the same window once before HhP and once
after it (HhP is compared with their mean), in one process: the Atari target's comparison::

    python benchmarks/speed.py entry --env ALE/MontezumaRevenge-v5 --start 1000 --stop 2000 --vs-dqn

with ``--vs-her`` (Fetch), against SB3's DDPG + HER (``HerReplayBuffer``, future strategy, 4 goals a transition) with
the goal-conditioned learner's network sizes, batch size, discount, learning rate and update rate (its gradient
steps per primitive step), on the raw dict envs, timed as ``--vs-dqn``: the Fetch target's comparison::

    python benchmarks/speed.py entry --env FetchPush-v4 --start 2000 --stop 4000 --vs-her

``call``: one grouped call of the sub-goal learners' update (``train_rounds``: the two rounds due at a step of the
envs, each of the entry's ``max_updates`` learners) from one saved state of a run (as ``ab``), repeated, its time split
with torch's profiler into the batched matrix products (``baddbmm``, ``bmm``: the arithmetic), torch's other
operators (gathers, concatenations, the loss, Adam, the clip, ...) and what runs outside torch (drawing and
relabelling the batches, the priority update, Python; the profiled calls' wall time less torch's share); the call's
time unprofiled beside it::

    python benchmarks/speed.py call --env MiniGrid-DoorKey-8x8-v0 --n-envs 8 --seed 1 --start 25000

or from a run's checkpoint (``--model``, ``--replay``) instead of a state trained for it; with ``PYTHONPATH`` set to
another checkout (``git worktree add``) the same command times that code from the same state::

    python benchmarks/speed.py call --env MiniGrid-KeyCorridorS4R3-v0 --n-envs 8 --model CKPT/model.zip --replay CKPT/replay.pkl

With ``--call-ab``, ``--learners-a`` and ``--learners-b`` (as ``ab``) timed too, in alternating blocks of 25 calls::

    python benchmarks/speed.py call --env MiniGrid-KeyCorridorS4R3-v0 --n-envs 8 --seed 100 --start 60000 --repeats 6 \
        --call-ab --learners-a '{"keep_encoded": true}' --learners-b '{"keep_encoded": false}'

Results are JSON files under ``--out``; say the machine's load next to the figures (the script records the load
average at its start and end).
"""

import argparse
import cProfile
import json
import os
import pathlib
import pstats
import resource
import subprocess
import sys
import tempfile
import time
from typing import Any

import gymnasium as gym
import minigrid  # noqa: F401  (registers the MiniGrid envs)
import numpy as np
import torch as th
import yaml
from rl_zoo3.utils import get_wrapper_class
from stable_baselines3 import DDPG, DQN, HerReplayBuffer
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.type_aliases import TrainFreq, TrainFrequencyUnit

sys.path.append(str(pathlib.Path(__file__).resolve().parents[1]))  # run as a script: the benchmarks package
from benchmarks.run import code_version  # noqa: E402
import sb3_hhp  # noqa: E402
from sb3_hhp import HhP  # noqa: E402
from sb3_hhp.extras import import_extra  # noqa: E402
from sb3_hhp.goals import register_minigrid_tasks, wrap_env  # noqa: E402
from sb3_hhp.hhp.arguments import SUBGOAL_LEARNER_DEFAULTS  # noqa: E402
from sb3_hhp.hierarchy.goal_conditioned import DEFAULT_KWARGS as GOAL_CONDITIONED_KWARGS  # noqa: E402
from sb3_hhp.hierarchy.learners import StackedDQN, default_subpolicy_kwargs  # noqa: E402
from sb3_hhp.train import ZOO_KEYS, default_config_path, select_entry  # noqa: E402


def yaml_entry(env_id: str) -> tuple[str, dict[str, Any]]:
    """The name and the whole entry of ``env_id`` in ``sb3_hhp/hyperparams/hhp.yml`` (ALE's envs registered for an
    ``ALE/`` id and gymnasium-robotics's for a ``Fetch`` one: its entry is its domain's)."""
    if env_id.startswith("ALE/"):
        gym.register_envs(import_extra("ale_py"))
    elif env_id.startswith("Fetch"):
        gym.register_envs(import_extra("gymnasium_robotics"))
    table = yaml.safe_load(default_config_path().read_text())
    name = select_entry(table, env_id)
    return name, table[name]


def entry_kwargs(env_id: str, overrides: str = "{}") -> tuple[str, dict[str, Any]]:
    """The YAML entry's HhP keyword arguments (RL Zoo's own keys left out), updated with ``overrides`` (JSON), its
    questions paced over the entry's run (:func:`paced_as_run`), and the entry's name."""
    name, entry = yaml_entry(env_id)
    return name, paced_as_run(entry, hhp_kwargs(entry, overrides))


def hhp_kwargs(entry: dict[str, Any], overrides: str = "{}") -> dict[str, Any]:
    """A YAML entry's HhP keyword arguments (RL Zoo's own keys left out), updated with ``overrides`` (JSON)."""
    return {**{key: value for key, value in entry.items() if key not in ZOO_KEYS}, **json.loads(overrides)}


def as_trained(kwargs: dict[str, Any], folder: pathlib.Path) -> dict[str, Any]:
    """``kwargs`` as ``sb3_hhp.train`` completes them: the scripted oracle, and a preference file in the run's folder
    (what the store and the per-choice work cost is measured with it)."""
    folder.mkdir(parents=True, exist_ok=True)
    return {"oracle": "scripted", "preference_db": str(folder / "preferences.sqlite"), **kwargs}


def paced_as_run(entry: dict[str, Any], kwargs: dict[str, Any]) -> dict[str, Any]:
    """``kwargs`` with the questions paced over the entry's ``n_timesteps`` (``query_kwargs["horizon"]``) unless they
    name a horizon: a window of a few thousand steps then asks what those steps of the real run would ask, not the
    whole budget (the adaptive pacing spreads it over the ``learn`` call's length)."""
    query = dict(kwargs.get("query_kwargs") or {})
    if query.get("horizon") is None and "n_timesteps" in entry:
        query["horizon"] = int(float(entry["n_timesteps"]))
    return {**kwargs, "query_kwargs": query}


def timed_steps(model: Any, steps: int) -> float:
    """Train ``model`` on for ``steps`` primitive steps: primitive steps per second."""
    begin, before = time.perf_counter(), model.num_timesteps
    model.learn(steps, reset_num_timesteps=False)
    return (model.num_timesteps - before) / (time.perf_counter() - begin)


def clocked(method: Any, spent: Any, key: Any) -> Any:
    """``method`` with a clock around each call: its seconds added to ``spent[key]``."""
    def call(*args: Any, **kwargs: Any) -> Any:
        begin = time.perf_counter()
        try:
            return method(*args, **kwargs)
        finally:
            spent[key] += time.perf_counter() - begin
    return call


def timed_window(model: Any, start: int, stop: int) -> float:
    """Train ``model`` to ``start`` steps untimed, then to ``stop`` timed: primitive steps per second over the window."""
    model.learn(start)
    return timed_steps(model, stop - model.num_timesteps)


def make_envs(env_id: str, n_envs: int, seed: int, wrapper: Any = wrap_env) -> Any:
    """``n_envs`` envs as RL Zoo builds them for the YAML entry (``wrapper``: its ``env_wrapper``, by default the goal
    space's observation; its ``env_kwargs``, ALE's ``frameskip: 1``, passed to ``gym.make``)."""
    env_kwargs = yaml_entry(env_id)[1].get("env_kwargs")
    return make_vec_env(env_id, n_envs=n_envs, wrapper_class=wrapper, seed=seed, env_kwargs=env_kwargs)


def ratio(args: argparse.Namespace) -> dict[str, Any]:
    entry, kwargs = entry_kwargs(args.env, args.hhp_kwargs)
    dqn, learning = flat_dqn(args, kwargs)
    dqn_before = timed_window(dqn, args.start, args.stop)
    folder = pathlib.Path(tempfile.mkdtemp(prefix="hhp_speed_"))
    hhp = HhP("MlpPolicy", make_envs(args.env, args.n_envs, args.seed), seed=args.seed, **as_trained(kwargs, folder))
    hhp_fps = timed_window(hhp, args.start, args.stop)
    # the flat DQN timed again over as many steps right after HhP (a machine of this kind drifts): HhP is compared
    # with the mean of the two
    dqn_after = timed_steps(dqn, args.stop - args.start)
    dqn_fps = (dqn_before + dqn_after) / 2
    profiler = cProfile.Profile()
    profiler.enable()
    hhp.learn(args.profile_steps, reset_num_timesteps=False)
    profiler.disable()
    write_profile(profiler, pathlib.Path(args.out) / f"{args.name or 'ratio'}_profile.txt",
                  f"HhP ({entry} entry) on {args.env}, {args.profile_steps} steps after step {args.stop}, "
                  f"{len(hhp.subgoals)} sub-goals")
    return dict(env=args.env, entry=entry, hhp_kwargs=json.loads(args.hhp_kwargs), window=[args.start, args.stop],
                seed=args.seed, n_envs=args.n_envs, dqn_fps=round(dqn_fps, 1), dqn_fps_before=round(dqn_before, 1),
                dqn_fps_after=round(dqn_after, 1),
                hhp_fps=round(hhp_fps, 1), ratio=round(hhp_fps / dqn_fps, 3), num_subgoals=len(hhp.subgoals),
                dqn_learning=learning)


def flat_dqn(args: argparse.Namespace, kwargs: dict[str, Any]) -> tuple[DQN, dict[str, Any]]:
    """Flat SB3 DQN doing the sub-goal learners' work per primitive step (their network, train_freq, batch size)."""
    sub = {**default_subpolicy_kwargs(), **kwargs.get("subpolicy_kwargs", {})}
    net_arch = (sub.get("policy_kwargs") or {}).get("net_arch", [64, 64])
    dqn = DQN("MlpPolicy", make_envs(args.env, args.n_envs, args.seed), learning_starts=sub["learning_starts"],
              batch_size=sub["batch_size"], train_freq=sub["train_freq"], gradient_steps=max(1, args.n_envs // sub["train_freq"]),
              buffer_size=50_000, policy_kwargs=dict(net_arch=net_arch), seed=args.seed,
              device=kwargs.get("device", "auto"))  # where HhP's networks are (``--hhp-kwargs '{"device": "cpu"}'``)
    if args.n_envs > 1:  # SB3's train_freq counts steps of the VecEnv: one update per train_freq primitive steps
        dqn.train_freq = TrainFreq(1, TrainFrequencyUnit.STEP)
    return dqn, dict(net_arch=net_arch, train_freq=sub["train_freq"], batch_size=sub["batch_size"])


def entry_speed(args: argparse.Namespace) -> dict[str, Any]:
    """HhP as the env's YAML entry trains it (its policy, ``env_wrapper`` and ``n_envs`` unless ``--n-envs`` says
    otherwise), timed over steps ``--start`` to ``--stop``, with ``--hhp-kwargs`` over the entry's (e.g. the device)."""
    _, entry = yaml_entry(args.env)
    kwargs = paced_as_run(entry, hhp_kwargs(entry, args.hhp_kwargs))  # the YAML read once
    wrapper = get_wrapper_class(entry)  # the entry's env_wrapper, as RL Zoo reads it
    n_envs = args.n_envs or entry.get("n_envs", 1)
    policy = entry.get("policy", "MlpPolicy")
    baseline, compared = None, {}
    if args.vs_her:
        baseline, compared["her"] = her_baseline(args, kwargs, n_envs)
        compared["her_fps_before"] = timed_window(baseline, args.start, args.stop)
    elif args.vs_dqn:  # SB3's DQN on the same envs: train_freq 4 and batch 32, one update per 4 primitive steps
        baseline = DQN(policy, make_envs(args.env, n_envs, args.seed, wrapper), batch_size=32,
                       train_freq=4 if n_envs == 1 else TrainFreq(1, TrainFrequencyUnit.STEP),
                       gradient_steps=max(1, n_envs // 4), buffer_size=50_000, learning_starts=min(100, args.start),
                       seed=args.seed, device=kwargs.get("device", "auto"))
        compared["dqn_fps_before"] = timed_window(baseline, args.start, args.stop)
    folder = pathlib.Path(tempfile.mkdtemp(prefix="hhp_speed_"))
    model = HhP(policy, make_envs(args.env, n_envs, args.seed, wrapper), seed=args.seed, **as_trained(kwargs, folder))
    fps = timed_window(model, args.start, args.stop)
    if baseline is not None:  # again right after HhP, over as many steps (the machine drifts): HhP against the mean
        name = "her" if args.vs_her else "dqn"
        compared[f"{name}_fps_after"] = timed_steps(baseline, args.stop - args.start)
        compared[f"{name}_fps"] = (compared[f"{name}_fps_before"] + compared[f"{name}_fps_after"]) / 2
        compared = {key: round(value, 2) if isinstance(value, float) else value for key, value in compared.items()}
        compared["ratio"] = round(fps / compared[f"{name}_fps"], 3)
    return dict(env=args.env, hhp_kwargs=json.loads(args.hhp_kwargs), window=[args.start, args.stop], seed=args.seed,
                n_envs=n_envs, policy=policy, device=str(model.device), hhp_fps=round(fps, 2), **compared,
                num_subgoals=len(model.subgoals), meta_updates=model._n_updates,
                peak_rss_mb=round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1))


def write_profile(profiler: cProfile.Profile, path: pathlib.Path, title: str) -> None:
    with open(path, "w") as handle:
        stats = pstats.Stats(profiler, stream=handle)
        handle.write(title + "\n")
        stats.sort_stats("cumulative").print_stats(45)
        stats.sort_stats("tottime").print_stats(25)


def saved_run(args: argparse.Namespace) -> HhP:
    """The saved model ``--model`` on fresh envs, its replays filled from ``--replay`` when given; no more questions
    (a run's budget is spent by its end)."""
    hhp = HhP.load(args.model, env=make_envs(args.env, args.n_envs, args.seed), device="cpu")
    if args.replay:
        hhp.load_replay_buffer(args.replay)
    hhp.oracle = None
    return hhp


def late(args: argparse.Namespace) -> dict[str, Any]:
    if not args.model:
        raise SystemExit("late needs --model: a saved HhP model (e.g. a benchmark run's model zip)")
    entry, kwargs = entry_kwargs(args.env, args.hhp_kwargs)
    hhp = saved_run(args)
    start_steps = hhp.num_timesteps
    hhp_fps = timed_steps(hhp, args.profile_steps)
    shares = timed_parts(hhp, args.profile_steps)
    profiler = cProfile.Profile()
    profiler.enable()
    hhp.learn(args.profile_steps, reset_num_timesteps=False)
    profiler.disable()
    write_profile(profiler, pathlib.Path(args.out) / f"{args.name or 'late'}_profile.txt",
                  f"HhP ({args.model}) on {args.env}, {args.profile_steps} steps after step {hhp.num_timesteps - args.profile_steps}, "
                  f"{args.n_envs} envs, {len(hhp.subgoals)} sub-goals")
    dqn, learning = flat_dqn(args, kwargs)
    dqn_fps = timed_window(dqn, args.start, args.start + args.profile_steps)
    return dict(env=args.env, model=args.model, replay=args.replay,
                from_step=start_steps, steps=args.profile_steps, n_envs=args.n_envs,
                hhp_fps=round(hhp_fps, 1), dqn_fps=round(dqn_fps, 1), ratio=round(hhp_fps / dqn_fps, 3),
                num_subgoals=len(hhp.subgoals), dqn_learning=learning, shares=shares)


#: the parts of a step :func:`timed_parts` times: (where the method is, its name, the label); nested parts after
#: the part that holds them
PARTS = (("model", "train", "meta-controller updates"), ("model", "_rewards", "meta-controller updates: eq. 3 rewards"),
         ("model", "_target", "meta-controller updates: Double DQN targets"),
         ("learners", "train_rounds", "sub-goal learners' updates"), ("model", "after_episode", "between episodes"))


def timed_parts(hhp: HhP, steps: int) -> dict[str, Any]:
    """Train ``hhp`` on for ``steps`` primitive steps with a clock around each part of :data:`PARTS` (a few
    microseconds a call, where cProfile's per-call cost inflates Python-heavy parts): its seconds and share of the
    whole; the methods are restored after."""
    owners = {"model": hhp, "learners": hhp.subpolicies}
    spent: dict[str, float] = {label: 0.0 for _, _, label in PARTS}
    try:
        for owner, name, label in PARTS:
            setattr(owners[owner], name, clocked(getattr(owners[owner], name), spent, label))
        before = hhp.num_timesteps
        fps = timed_steps(hhp, steps)
        done = hhp.num_timesteps - before
        total = done / fps
    finally:
        for owner, name, _ in PARTS:
            vars(owners[owner]).pop(name, None)  # the class's method again
    return dict(steps=done, seconds=round(total, 2), fps=round(fps, 1),
                parts={label: dict(seconds=round(value, 2), share=round(value / total, 3)) for label, value in spent.items()})


def snapshot(args: argparse.Namespace, kwargs: dict[str, Any], prefix: str) -> tuple[HhP, pathlib.Path]:
    """HhP trained to ``--start`` steps, saved with its replays in a fresh folder: the model and the folder."""
    folder = pathlib.Path(tempfile.mkdtemp(prefix=prefix))
    hhp = HhP("MlpPolicy", make_envs(args.env, args.n_envs, args.seed), seed=args.seed, **as_trained(kwargs, folder))
    hhp.learn(args.start)
    hhp.save(folder / "snapshot.zip")
    hhp.save_replay_buffer(folder / "snapshot_replay.pkl")
    return hhp, folder


def from_snapshot(args: argparse.Namespace, folder: pathlib.Path, repeat: int) -> HhP:
    """The :func:`snapshot` of ``folder`` loaded with its replays, on fresh envs of their own (one seed a repeat)."""
    model = HhP.load(folder / "snapshot.zip", env=make_envs(args.env, args.n_envs, args.seed + 1 + repeat))
    model.load_replay_buffer(folder / "snapshot_replay.pkl")
    return model


def set_learners(learners: Any, values: dict[str, Any]) -> None:
    """The sub-goal learners' attributes ``values`` (e.g. grouped_rounds, max_updates); ``keep_encoded``: whether their
    replay keeps what the networks read of its states (with one_hot, the places of the set indicators)."""
    for key, value in values.items():
        if key == "keep_encoded":
            learners.replay.keep_encoded(learners._encoded if value else None)
        else:
            setattr(learners, key, value)


def learners_ab(args: argparse.Namespace) -> dict[str, Any]:
    """HhP trained to ``--start`` steps and saved with its replays; then ``--repeats`` times, alternately, loaded and
    trained ``--profile-steps`` more with the learner settings of ``--learners-a`` and of ``--learners-b``: two
    settings of the sub-goal learners from one state, timed side by side (the machine drifts)."""
    _, kwargs = entry_kwargs(args.env, args.hhp_kwargs)
    hhp, folder = snapshot(args, kwargs, "hhp_ab_")
    settings = {"a": json.loads(args.learners_a), "b": json.loads(args.learners_b)}
    fps: dict[str, list[float]] = {"a": [], "b": []}
    subgoals: dict[str, list[int]] = {"a": [], "b": []}
    for repeat in range(args.repeats):
        for name, values in settings.items():
            model = from_snapshot(args, folder, repeat)
            set_learners(model.subpolicies, values)
            fps[name].append(round(timed_steps(model, args.profile_steps), 1))
            subgoals[name].append(len(model.subgoals))
    ratios = np.array(fps["b"]) / np.array(fps["a"])
    return dict(env=args.env, snapshot_steps=hhp.num_timesteps, snapshot_subgoals=len(hhp.subgoals), steps=args.profile_steps,
                n_envs=args.n_envs, learners_a=settings["a"], learners_b=settings["b"], fps_a=fps["a"], fps_b=fps["b"],
                subgoals_a=subgoals["a"], subgoals_b=subgoals["b"], median_ratio_b_to_a=round(float(np.median(ratios)), 3))


def parts(args: argparse.Namespace) -> dict[str, Any]:
    """HhP trained to ``--start`` steps and saved with its replays; then ``--repeats`` times, alternately, trained
    ``--profile-steps`` more from that state as it is (the seconds inside ``train_rounds``, the sub-goal learners'
    grouped updates, counted) and with those updates left out; the flat DQN as in ``ratio``."""
    entry, kwargs = entry_kwargs(args.env, args.hhp_kwargs)
    dqn, learning = flat_dqn(args, kwargs)
    dqn_before = timed_window(dqn, args.start, args.start + args.profile_steps)
    hhp, folder = snapshot(args, kwargs, "hhp_parts_")
    fps: dict[str, list[float]] = {"full": [], "no_updates": []}
    update_ms, learner_updates = [], []
    for repeat in range(args.repeats):
        for name in fps:
            model = from_snapshot(args, folder, repeat)
            learners, spent = model.subpolicies, [0.0]
            updates_before = int(learners.n_updates.sum())
            # an instance attribute: the learners' own method is not changed for other models
            learners.train_rounds = (clocked(learners.train_rounds, spent, 0) if name == "full"
                                     else (lambda plan, first_round=0: 0.0))
            steps_before = model.num_timesteps
            fps[name].append(round(timed_steps(model, args.profile_steps), 1))
            if name == "full":  # learn() ends with an episode: count the steps it made
                vec_steps = (model.num_timesteps - steps_before) / args.n_envs
                update_ms.append(round(1000 * spent[0] / vec_steps, 3))
                learner_updates.append(round((int(learners.n_updates.sum()) - updates_before) / vec_steps, 2))
    dqn_after = timed_steps(dqn, args.profile_steps)
    dqn_fps = (dqn_before + dqn_after) / 2
    full, bare = float(np.median(fps["full"])), float(np.median(fps["no_updates"]))
    vec_ms = lambda steps_per_s: 1000 * args.n_envs / steps_per_s  # noqa: E731  (ms a step of the n envs)
    return dict(env=args.env, entry=entry, hhp_kwargs=json.loads(args.hhp_kwargs), seed=args.seed, n_envs=args.n_envs,
                snapshot_steps=hhp.num_timesteps, snapshot_subgoals=len(hhp.subgoals), steps=args.profile_steps,
                fps_full=fps["full"], fps_without_learner_updates=fps["no_updates"],
                learner_updates_ms_per_vec_step=update_ms, learner_updates_per_vec_step=learner_updates,
                dqn_fps=round(dqn_fps, 1), dqn_fps_before=round(dqn_before, 1), dqn_fps_after=round(dqn_after, 1),
                ratio=round(full / dqn_fps, 3), ratio_without_learner_updates=round(bare / dqn_fps, 3),
                ms_per_vec_step=dict(hhp=round(vec_ms(full), 3), hhp_without_learner_updates=round(vec_ms(bare), 3),
                                     dqn=round(vec_ms(dqn_fps), 3), half_dqn_speed=round(2 * vec_ms(dqn_fps), 3)),
                dqn_learning=learning)


def learner_call(args: argparse.Namespace) -> dict[str, Any]:
    """One grouped call of the sub-goal learners from a saved state, timed and split by torch's profiler."""
    from torch.profiler import ProfilerActivity, profile

    _, kwargs = entry_kwargs(args.env, args.hhp_kwargs)
    hhp = saved_run(args) if args.model else snapshot(args, kwargs, "hhp_call_")[0]
    learners = hhp.subpolicies  # the state is timed once: no need to load the saved copy back
    goals = np.arange(min(len(learners), learners.max_updates or len(learners)))
    plan = [goals] * max(1, args.n_envs // learners.train_freq)  # the rounds due at one step of the envs

    def call() -> None:
        learners.train_rounds(plan, first_round=learners.rounds + 1)

    calls = args.repeats * 25
    compared = {}
    if args.call_ab:  # --learners-b against --learners-a, blocks of calls alternately from this state (the machine drifts)
        settings = {"a": json.loads(args.learners_a), "b": json.loads(args.learners_b)}
        blocks: dict[str, list[float]] = {"a": [], "b": []}
        for _ in range(args.repeats):
            for name, values in settings.items():
                set_learners(learners, values)
                blocks[name].append(round(1000 * median_seconds(call, 25, blocks=1), 3))
        compared = dict(learners_a=settings["a"], learners_b=settings["b"], call_ms_a=blocks["a"], call_ms_b=blocks["b"],
                        median_ratio_b_to_a=round(float(np.median(np.array(blocks["b"]) / np.array(blocks["a"]))), 3))
        set_learners(learners, settings["a"])  # the split below: A's
    seconds = median_seconds(call, calls)  # as a run pays it
    with profile(activities=[ProfilerActivity.CPU]) as prof:  # the split, from a profiled run of as many calls
        begin = time.perf_counter()
        for _ in range(calls):
            call()
        profiled_ms = 1000 * (time.perf_counter() - begin) / calls
    events = prof.key_averages()
    torch_ms = sum(event.self_cpu_time_total for event in events) / 1000 / calls
    products_ms = sum(event.self_cpu_time_total for event in events if event.key in ("aten::baddbmm", "aten::bmm")) / 1000 / calls
    top = sorted(events, key=lambda event: -event.self_cpu_time_total)[:12]
    return dict(env=args.env, seed=args.seed, n_envs=args.n_envs, model=args.model, replay=args.replay,
                snapshot_steps=hhp.num_timesteps,
                snapshot_subgoals=len(hhp.subgoals), learners_per_round=len(goals), rounds=len(plan),
                call_ms=round(1000 * seconds, 3), profiled_call_ms=round(profiled_ms, 3), products_ms=round(products_ms, 3),
                other_torch_ms=round(torch_ms - products_ms, 3), outside_torch_ms=round(profiled_ms - torch_ms, 3),
                top_torch_ops_ms={event.key: round(event.self_cpu_time_total / 1000 / calls, 3) for event in top}, **compared)


def her_baseline(args: argparse.Namespace, kwargs: dict[str, Any], n_envs: int) -> tuple[DDPG, dict[str, Any]]:
    """SB3's DDPG + HER doing the goal-conditioned learner's work per primitive step (its network sizes, batch
    size, discount, learning rate, gradient steps a step and learning start), on the raw dict envs; and those settings."""
    sub = {**GOAL_CONDITIONED_KWARGS, **kwargs.get("subpolicy_kwargs", {})}
    same = dict(batch_size=sub["batch_size"], gamma=sub["gamma"], learning_rate=sub["learning_rate"],
                gradient_steps=sub["gradient_steps"] * n_envs, learning_starts=sub["learning_starts"])
    net_arch = sub["policy_kwargs"]["net_arch"]
    model = DDPG("MultiInputPolicy", make_envs(args.env, n_envs, args.seed, wrapper=None), train_freq=1,
                 replay_buffer_class=HerReplayBuffer,
                 replay_buffer_kwargs=dict(n_sampled_goal=4, goal_selection_strategy="future"),
                 buffer_size=100_000, policy_kwargs=dict(net_arch=net_arch), seed=args.seed,
                 device=kwargs.get("device", "auto"), **same)
    return model, dict(algo="DDPG + HER", net_arch=net_arch, hhp_learner=sub["algo"], **same)


def fetch_states(env: gym.Env, space: Any, n: int, seed: int) -> list[np.ndarray]:
    """``n`` observations of a Fetch env (flat) with the achieved position in ``n`` distinct cells: a reset state
    whose achieved position is moved over a lattice 6 cm apart around where it starts (random play seldom moves
    an object)."""
    obs, _ = env.reset(seed=seed)
    side = int(np.ceil(n ** (1 / 3)))
    offsets = (np.stack(np.meshgrid(*[np.arange(side)] * 3, indexing="ij"), -1).reshape(-1, 3) - (side - 1) / 2) * 0.06
    states = []
    for offset in offsets[:n]:
        state = obs.copy()
        state[-6:-3] += offset.astype(state.dtype)
        states.append(state)
    assert len({space.key(state) for state in states}) == n
    return states


def distinct_states(env_id: str, n: int, seed: int, wrapper: Any = wrap_env) -> list[np.ndarray]:
    """``n`` observations from random play (the env wrapped with ``wrapper``), of as many distinct sub-goal keys as
    the env shows (then repeated); on Fetch, ``n`` distinct places (:func:`fetch_states`)."""
    from sb3_hhp.goals import FetchGoalSpace, make_goal_space

    env = wrapper(gym.make(env_id))
    space = make_goal_space("auto", env)
    if isinstance(space, FetchGoalSpace):
        return fetch_states(env, space, n, seed)
    rng = np.random.default_rng(seed)
    by_key: dict[Any, np.ndarray] = {}
    for episode in range(50):
        obs, _ = env.reset(seed=seed + episode)
        done = False
        while not done:
            by_key.setdefault(space.key(obs), obs)
            obs, _, terminated, truncated, _ = env.step(int(rng.integers(env.action_space.n)))
            done = terminated or truncated
    states = list(by_key.values())
    return [states[i % len(states)] for i in range(n)]


def one_subgoal_count(args: argparse.Namespace) -> dict[str, Any]:
    """In this process: HhP with ``args.k`` sub-goals handed in; seconds per primitive step and peak memory."""
    _, entry = yaml_entry(args.env)
    kwargs, wrapper = hhp_kwargs(entry, args.hhp_kwargs), get_wrapper_class(entry)  # the entry's policy and envs
    subgoals = distinct_states(args.env, args.k, args.seed, wrapper)
    # Montezuma's scripted oracle reads the facts of the states where sub-goals were found, which sub-goals handed in
    # lack: on Atari no questions are asked (a cost that does not depend on K)
    oracle = "none" if args.env.startswith("ALE/") else "scripted"
    kwargs.update(oracle=oracle, discovery_kwargs=dict(strategy="none", subgoals=subgoals))
    model = HhP(entry.get("policy", "MlpPolicy"), make_envs(args.env, args.n_envs, args.seed, wrapper), seed=args.seed, **kwargs)
    fps = timed_window(model, args.start, args.stop)
    return dict(k=args.k, oracle=oracle, fps=round(fps, 1), ms_per_step=round(1000 / fps, 3),
                peak_rss_mb=round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
                replay_mb=round(model.subpolicies.replay.nbytes() / 2**20, 1))


def subgoals(args: argparse.Namespace) -> dict[str, Any]:
    rows = []
    for k in args.counts:
        command = [sys.executable, __file__, "one", "--env", args.env, "--k", str(k), "--seed", str(args.seed),
                   "--start", str(args.start), "--stop", str(args.stop), "--hhp-kwargs", args.hhp_kwargs,
                   "--n-envs", str(args.n_envs), "--threads", str(args.threads)]
        rows.append(json.loads(subprocess.run(command, check=True, capture_output=True, text=True).stdout.splitlines()[-1]))
        print(json.dumps(rows[-1]), flush=True)
    low, high = rows[0], rows[-1]
    return dict(env=args.env, window=[args.start, args.stop], seed=args.seed, hhp_kwargs=json.loads(args.hhp_kwargs), rows=rows,
                cost_ratio=round(high["ms_per_step"] / low["ms_per_step"], 3),
                memory_ratio=round(high["peak_rss_mb"] / low["peak_rss_mb"], 3),
                replay_ratio=round(high["replay_mb"] / max(low["replay_mb"], 1e-9), 3))


def median_seconds(call: Any, repeats: int, blocks: int = 5) -> float:
    """The median over ``blocks`` blocks of the mean seconds of ``call()`` over ``repeats`` calls (after a warm-up)."""
    for _ in range(max(1, repeats // 10)):
        call()
    times = []
    for _ in range(blocks):
        begin = time.perf_counter()
        for _ in range(repeats):
            call()
        times.append((time.perf_counter() - begin) / repeats)
    return float(np.median(times))


def floor(args: argparse.Namespace) -> dict[str, Any]:
    _, kwargs = entry_kwargs(args.env, args.hhp_kwargs)
    envs = make_envs(args.env, args.n_envs, args.seed)
    envs.reset()
    rng = np.random.default_rng(args.seed)
    env_seconds = median_seconds(lambda: envs.step(rng.integers(envs.action_space.n, size=args.n_envs)), 200) / args.n_envs
    # the sub-goal learners as HhP builds them, with as many learners as one round updates at most
    learner_kwargs = {**SUBGOAL_LEARNER_DEFAULTS, **kwargs.get("subgoal_learner_kwargs", {})}
    k = int(learner_kwargs["max_updates"] or 8)
    learners = StackedDQN(envs.observation_space, envs.action_space, achieved=lambda key, goal: key == goal,
                          subpolicy_kwargs=kwargs.get("subpolicy_kwargs"), n_envs=args.n_envs, seed=args.seed)
    for goal in range(k):
        learners.add(goal)
    if not learners._relu_mlp:
        raise SystemExit("floor times the written-out update of a ReLU MLP (MlpPolicy); this entry's learners are not one")
    batch, closing = learners.batch_size, 2 * learners.batch_size if learners.replay.lower_bound else learners.batch_size
    obs = th.as_tensor(np.stack([envs.observation_space.sample() for _ in range(k * (batch + closing))]))
    x_online = learners._mlp_input(obs.reshape(k, batch + closing, *obs.shape[1:]))
    x_target = x_online[:, batch:].contiguous()
    params, goals = learners.params[:k], np.arange(k)
    grad_q = th.randn(k, batch, int(envs.action_space.n)) / batch

    def products() -> th.Tensor:
        outputs = learners._mlp_forward(params, x_online)
        with th.no_grad():
            learners._mlp_forward(learners.target[:k], x_target)
        return learners._mlp_backward(params, outputs, grad_q)

    products_seconds = median_seconds(products, 100)
    with_adam_seconds = median_seconds(lambda: learners._adam(goals, learners._clip(products()), 1), 100)
    rounds_per_step = 1 / learners.train_freq
    cap = lambda seconds: 1 / (env_seconds + rounds_per_step * seconds)  # noqa: E731
    return dict(env=args.env, n_envs=args.n_envs, learners_per_round=k, batch_size=batch, rows_online=batch + closing,
                rows_target=closing, input_size=int(x_online.shape[-1]), train_freq=learners.train_freq,
                gradient_floats=int(params.numel()),
                env_steps_per_s=round(1 / env_seconds, 1), round_products_ms=round(1000 * products_seconds, 3),
                round_with_adam_ms=round(1000 * with_adam_seconds, 3),
                products_steps_per_s=round(1 / (rounds_per_step * products_seconds), 1),
                cap_steps_per_s=round(cap(products_seconds), 1), cap_with_adam_steps_per_s=round(cap(with_adam_seconds), 1))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("what", choices=["ratio", "late", "subgoals", "ab", "one", "floor", "parts", "entry", "call"])
    parser.add_argument("--env", default="MiniGrid-DoorKey-8x8-v0")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--start", type=int, default=20_000, help="primitive steps before the timed window")
    parser.add_argument("--stop", type=int, default=30_000, help="primitive steps at the end of the timed window")
    parser.add_argument("--profile-steps", type=int, default=5_000)
    parser.add_argument("--n-envs", type=int, default=None,
                        help="envs stepped together (HhP and the flat DQN alike; default 1, entry: the entry's n_envs)")
    parser.add_argument("--counts", type=int, nargs="+", default=[2, 32], help="sub-goal counts (subgoals)")
    parser.add_argument("--k", type=int, default=2, help=argparse.SUPPRESS)
    parser.add_argument("--hhp-kwargs", default="{}", help="JSON: HhP arguments over the entry's, e.g. '{\"subgoal_learner\": \"heads\"}'")
    parser.add_argument("--model", default=None, help="late, call: a saved HhP model (call: instead of --start steps)")
    parser.add_argument("--replay", default=None, help="late, call: the learners' replays saved with --model")
    parser.add_argument("--name", default=None, help="the result file's name (default: the measurement's)")
    parser.add_argument("--learners-a", default="{}", help="ab: JSON, sub-goal learner attributes of A")
    parser.add_argument("--learners-b", default='{"grouped_rounds": true}', help="ab: JSON, the same for B")
    parser.add_argument("--repeats", type=int, default=4, help="ab, parts: pairs; call: 25 calls a repeat")
    parser.add_argument("--vs-dqn", action="store_true", help="entry: SB3's DQN timed over the same window beside HhP")
    parser.add_argument("--vs-her", action="store_true",
                        help="entry (Fetch): SB3's DDPG + HER with the sub-goal learner's sizes, over the same window")
    parser.add_argument("--call-ab", action="store_true",
                        help="call: also time --learners-a against --learners-b, --repeats alternating blocks of 25 calls")
    parser.add_argument("--out", default="benchmarks/results/speed")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (HhP and the flat DQN alike)")
    args = parser.parse_args()
    th.set_num_threads(args.threads)
    register_minigrid_tasks()  # the paper's MultiRoom-N12-S10, as sb3_hhp.train registers it
    if args.what != "entry" and args.n_envs is None:
        args.n_envs = 1
    if args.what == "one":
        print(json.dumps(one_subgoal_count(args)))
        return
    pathlib.Path(args.out).mkdir(parents=True, exist_ok=True)
    load_before = os.getloadavg()[0]
    result = {"ratio": ratio, "late": late, "subgoals": subgoals, "ab": learners_ab, "floor": floor, "parts": parts,
              "entry": entry_speed, "call": learner_call}[args.what](args)
    result.update(threads=args.threads, load_average_start=round(load_before, 2), load_average_end=round(os.getloadavg()[0], 2),
                  command=" ".join(sys.argv), code=code_version(pathlib.Path(sb3_hhp.__file__).resolve().parents[1]))
    (pathlib.Path(args.out) / f"{args.name or args.what}.json").write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
