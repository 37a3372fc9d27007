"""The hyperparameter file of ``python -m sb3_hhp.train`` and the checks made before anything is trained.

The YAML file maps env ids to HhP's keyword arguments and RL Zoo's keys (:data:`ZOO_KEYS`). An env id with no entry
of its own takes its domain's (:data:`DOMAIN_KEYS`: ``minigrid`` for any ``MiniGrid-*`` id, ``atari``, ``fetch``),
else ``default``. Keys neither HhP's constructor (read from its signature) nor RL Zoo accepts are refused, with the
closest valid key, as :class:`ConfigError`: one line on the command line, before training starts.
"""

import contextlib
import difflib
import importlib
import inspect
import io
from collections.abc import Sequence
from pathlib import Path
from typing import Any, Optional

#: the algorithm's name in RL Zoo (``--algo hhp``, ``<log folder>/hhp/``)
ALGO_NAME = "hhp"
#: the file name of the preference database inside the run folder
PREFERENCE_DB_NAME = "preferences.sqlite"
#: keys RL Zoo reads itself (they never reach HhP's constructor)
ZOO_KEYS = frozenset(
    {"n_timesteps", "policy", "env_wrapper", "n_envs", "normalize", "frame_stack", "callback", "vec_env_wrapper",
     "env_kwargs", "monitor_kwargs"}
)
#: constructor arguments RL Zoo sets from the command line; a YAML file must not set them
COMMAND_LINE_KEYS = {"seed": "--seed", "verbose": "--verbose", "device": "--device", "tensorboard_log": "--tensorboard-log"}
#: the YAML entry a domain's env ids fall back to when they have no entry of their own
DOMAIN_KEYS = ("minigrid", "atari", "fetch")


class ConfigError(ValueError):
    """A wrong command line or hyperparameter file: reported in one line, before training starts."""


def default_config_path() -> Path:
    """``sb3_hhp/hyperparams/hhp.yml``: package data, found from the package so that any working directory and an
    installed wheel work."""
    path = Path(__file__).resolve().parent.parent / "hyperparams" / f"{ALGO_NAME}.yml"
    if not path.is_file():
        raise ConfigError(f"No default hyperparameter file: looked for {path}; pass one with --conf-file FILE")
    return path


def domain_of(env_id: str) -> Optional[str]:
    """The domain of a registered env id, whose YAML entry serves ids with no entry of their own.

    :param env_id: a gymnasium env id (registered)
    :return: "minigrid", "atari", "fetch" or None
    """
    import gymnasium as gym

    entry_point = str(gym.spec(env_id).entry_point)
    if "minigrid" in entry_point:
        return "minigrid"
    if "AtariEnv" in entry_point or "ale_py" in entry_point:
        return "atari"
    if "gymnasium_robotics" in entry_point and env_id.startswith("Fetch"):
        return "fetch"
    return None


def select_entry(table: dict[str, Any], env_id: str, config: str = "the hyperparameter file") -> str:
    """The key of ``table`` that holds ``env_id``'s hyperparameters: the id itself, else its domain's
    entry (:data:`DOMAIN_KEYS`), else ``default`` (RL Zoo's convention).

    :param table: the parsed YAML file (env id or domain -> hyperparameters)
    :param env_id: a registered gymnasium env id
    :param config: the file's name, for the error message
    """
    if not isinstance(table, dict):
        raise ConfigError(f"{config} must map env ids to hyperparameters, got {type(table).__name__}")
    if env_id in table:
        return env_id
    domain = domain_of(env_id)
    if domain is not None and domain in table:
        return domain
    if "default" in table:
        return "default"
    raise ConfigError(
        f"No hyperparameters for {env_id} in {config}: add an entry {env_id!r}"
        + (f" or {domain!r}" if domain else "")
        + f" (entries: {', '.join(map(str, table))})"
    )


def hhp_arguments() -> list[str]:
    """The keyword arguments of :class:`~sb3_hhp.hhp.hhp.HhP` a hyperparameter file may set."""
    from sb3_hhp.hhp import HhP

    excluded = {"self", "policy", "env", "_init_setup_model", *COMMAND_LINE_KEYS}
    return [name for name, parameter in inspect.signature(HhP.__init__).parameters.items()
            if name not in excluded and parameter.kind is not inspect.Parameter.VAR_KEYWORD]


def validate_hyperparams(hyperparams: dict[str, Any], where: str) -> None:
    """Refuse keys that neither HhP's constructor nor RL Zoo accepts, and settings HhP cannot run with.

    :param hyperparams: one env's hyperparameters, after RL Zoo's overrides (``--hyperparams``)
    :param where: where they came from, for the messages
    """
    from sb3_hhp.oracles.registry import ORACLE_NAMES

    valid = hhp_arguments()
    for key in hyperparams:
        if key in COMMAND_LINE_KEYS:
            raise ConfigError(f"{where}: {key!r} is set on the command line ({COMMAND_LINE_KEYS[key]}), not in the file")
        if key not in ZOO_KEYS and key not in valid:
            close = difflib.get_close_matches(str(key), [*valid, *ZOO_KEYS], n=1)
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            raise ConfigError(
                f"{where}: unknown hyperparameter {key!r}{hint}. Valid keys: HhP's arguments {', '.join(valid)}; "
                f"RL Zoo's {', '.join(sorted(ZOO_KEYS))}"
            )
    n_envs = hyperparams.get("n_envs", 1)
    if isinstance(n_envs, bool) or not isinstance(n_envs, int) or n_envs < 1:
        raise ConfigError(f"{where}: n_envs must be an integer >= 1, got {n_envs!r}")
    for key in ("normalize", "frame_stack", "vec_env_wrapper"):
        if hyperparams.get(key):
            raise ConfigError(
                f"{where}: {key!r} wraps the VecEnv, and HhP needs the plain env: use env_wrapper (a gym.Wrapper) instead"
            )
    oracle = hyperparams.get("oracle", "scripted")
    if isinstance(oracle, str) and oracle not in ORACLE_NAMES:
        raise ConfigError(f"{where}: unknown oracle {oracle!r}: use one of {', '.join(ORACLE_NAMES)}")


def check_env_id(env_id: Optional[str], gym_packages: Sequence[str] = ()) -> str:
    """Fail early, in one line, on a missing or unknown env id (suggesting the closest registered one).

    :param env_id: the ``--env`` value
    :param gym_packages: modules that register envs (``--gym-packages``)
    """
    import gymnasium as gym

    from sb3_hhp.extras import missing_extra_hint, register_fetch_envs
    from sb3_hhp.goals import register_minigrid_tasks

    register_fetch_envs()  # the Fetch tasks, with the [fetch] extra (rl_zoo3 does not register them)
    register_minigrid_tasks()  # the paper's MultiRoom-N12-S10
    with contextlib.redirect_stderr(io.StringIO()):  # gymnasium-robotics prints a notice on Adroit envs at import
        import rl_zoo3.import_envs  # noqa: F401  registers MiniGrid, ALE, ...

    if not env_id:
        raise ConfigError("--env ENV is required (e.g. --env MiniGrid-DoorKey-5x5-v0)")
    for module in gym_packages:
        try:
            importlib.import_module(module)
        except ImportError as error:
            raise ConfigError(f"--gym-packages: cannot import {module!r}: {error}") from error
    if env_id not in gym.envs.registry:
        close = difflib.get_close_matches(env_id, list(gym.envs.registry), n=1)
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        extra = missing_extra_hint(env_id)
        install = f"; it comes with an extra: {extra}" if extra else ""
        raise ConfigError(f"Unknown env id {env_id!r}{hint}: not in the gymnasium registry{install}")
    return env_id
