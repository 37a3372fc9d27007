"""Curiosity for any SB3 algorithm: a VecEnv wrapper that adds RND's intrinsic reward (eq. 7) to the env's reward.

    from stable_baselines3 import PPO
    from stable_baselines3.common.env_util import make_vec_env
    from sb3_hhp.curiosity import VecRNDReward
    from sb3_hhp.goals import wrap_env

    env = VecRNDReward(make_vec_env("MiniGrid-DoorKey-8x8-v0", n_envs=8, wrapper_class=wrap_env), intrinsic_coef=0.5)
    PPO("MlpPolicy", env).learn(300_000)  # "PPO + RND", the paper's flat baseline

With RL Zoo, the same wrapper goes in the hyperparameter file:
``vec_env_wrapper: {sb3_hhp.curiosity.VecRNDReward: {intrinsic_coef: 0.5}}``.
"""

from typing import Any, Optional

import numpy as np
import torch as th
from stable_baselines3.common.vec_env import VecEnv, VecEnvWrapper
from stable_baselines3.common.vec_env.base_vec_env import VecEnvStepReturn

from sb3_hhp.curiosity.rnd import RND

#: key of ``infos[i]`` holding the env's own (extrinsic) reward of the step
EXTRINSIC_KEY = "extrinsic_reward"
#: key of ``infos[i]`` holding the intrinsic reward r^i of the step (before ``intrinsic_coef``)
INTRINSIC_KEY = "intrinsic_reward"


class VecRNDReward(VecEnvWrapper):
    """
    Adds curiosity to the reward of a VecEnv: ``r_t = r^e_t + intrinsic_coef * r^i_t`` with
    ``r^i_t = ||f_hat(s_{t+1}) - f(s_{t+1})||^2 / std(R^i)`` the RND intrinsic reward (eq. 7, :class:`~sb3_hhp.curiosity.rnd.RND`),
    computed on the next observation ``s_{t+1}``: the observation the step returned, or, for an env whose
    episode ended at that step, ``infos[i]["terminal_observation"]`` (the returned one is already the next
    episode's first). The batch of ``n_envs`` next observations enters the RND's forward filter as
    consecutive rows, as :meth:`~sb3_hhp.curiosity.rnd.RND.intrinsic_reward` reads them.

    Every ``update_every`` calls to ``step`` the predictor is trained for ``n_epochs`` passes on the
    ``update_every * n_envs`` next observations seen since the last update (their statistics join the
    observation normalisation first), then the buffer is emptied.

    The env's own reward stays in ``infos[i]["extrinsic_reward"]`` and ``r^i_t`` in
    ``infos[i]["intrinsic_reward"]``. SB3's :class:`~stable_baselines3.common.monitor.Monitor` wraps each env
    inside the VecEnv (``make_vec_env`` puts it there), so the episode returns it reports (``infos[i]["episode"]``,
    ``rollout/ep_rew_mean``, ``evaluate_policy``) are extrinsic: curiosity never inflates them.

    :param venv: the VecEnv; its observation space must be a ``gymnasium.spaces.Box`` (vectors or images)
    :param intrinsic_coef: weight of the intrinsic reward (>= 0); 0 leaves the reward unchanged while the
        predictor still learns
    :param rnd_kwargs: keyword arguments of :class:`~sb3_hhp.curiosity.rnd.RND` (``embedding_dim``, ``hidden_dim``, ``learning_rate``,
        ``gamma``, ``obs_clip``, ``batch_size``, ``device``, ``seed``, ...)
    :param update_every: VecEnv steps between two predictor updates (>= 1)
    :param n_epochs: passes over the buffered observations per update (>= 1)
    """

    def __init__(
        self,
        venv: VecEnv,
        intrinsic_coef: float = 1.0,
        rnd_kwargs: Optional[dict[str, Any]] = None,
        update_every: int = 128,
        n_epochs: int = 1,
    ) -> None:
        if not intrinsic_coef >= 0:
            raise ValueError(f"intrinsic_coef must be >= 0, got {intrinsic_coef}")
        for name, value in (("update_every", update_every), ("n_epochs", n_epochs)):
            if int(value) != value or value < 1:
                raise ValueError(f"{name} must be an integer >= 1, got {value}")
        super().__init__(venv)
        self.intrinsic_coef = float(intrinsic_coef)
        self.update_every = int(update_every)
        self.n_epochs = int(n_epochs)
        self.rnd = RND(venv.observation_space, **(rnd_kwargs or {}))  # refuses non-Box spaces, saying so
        self._buffer: list[np.ndarray] = []
        #: mean predictor loss of the last update (None before the first)
        self.last_loss: Optional[float] = None
        #: number of predictor updates so far
        self.n_updates = 0

    def reset(self) -> np.ndarray:
        return self.venv.reset()

    def step_wait(self) -> VecEnvStepReturn:
        obs, rewards, dones, infos = self.venv.step_wait()
        next_obs = np.array(obs, copy=True)
        for i, done in enumerate(dones):
            if done and infos[i].get("terminal_observation") is not None:
                next_obs[i] = infos[i]["terminal_observation"]
        intrinsic = self.rnd.intrinsic_reward(next_obs)  # eq. 7, on s_{t+1}
        extrinsic = np.asarray(rewards, dtype=np.float32)
        for i, info in enumerate(infos):
            info[EXTRINSIC_KEY] = float(extrinsic[i])
            info[INTRINSIC_KEY] = float(intrinsic[i])
        self.rnd.on_steps(self.num_envs)
        self._buffer.append(next_obs)
        if len(self._buffer) >= self.update_every:
            self.last_loss = self.rnd.update(np.concatenate(self._buffer), n_epochs=self.n_epochs)
            self.n_updates += 1
            self._buffer.clear()
        return obs, extrinsic + self.intrinsic_coef * intrinsic, dones, infos

    def state_dict(self) -> dict[str, Any]:
        """
        Everything needed to go on exactly where this wrapper stands (a checkpointed run resumed): the RND's state
        (:meth:`~sb3_hhp.curiosity.rnd.RND.state_dict`), the next observations buffered for the next predictor update (as tensors), the
        update count and the last loss. Tensors and plain Python data: written with ``th.save``, read back with
        ``th.load(..., weights_only=True)``.

        :return: the state
        """
        return {
            "rnd": self.rnd.state_dict(),
            "buffer": [th.from_numpy(np.array(obs, copy=True)) for obs in self._buffer],
            "n_updates": int(self.n_updates),
            "last_loss": self.last_loss,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """
        Restore a state produced by :meth:`state_dict` of a wrapper built with the same observation space and RND
        sizes.

        :param state: the state
        :raises ValueError: a state whose buffered observations do not fit this wrapper's env (say what differs)
        """
        buffer = [np.asarray(obs.numpy() if isinstance(obs, th.Tensor) else obs) for obs in state["buffer"]]
        expected = (self.num_envs, *self.observation_space.shape)
        for obs in buffer:
            if obs.shape != expected:
                raise ValueError(
                    f"The saved VecRNDReward buffered observations of shape {obs.shape}, this one's env gives "
                    f"{expected}: restore it around an env with the same number of envs and observation space"
                )
        self.rnd.load_state_dict(state["rnd"])
        self._buffer = buffer
        self.n_updates = int(state["n_updates"])
        self.last_loss = None if state["last_loss"] is None else float(state["last_loss"])
