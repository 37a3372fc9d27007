"""Optional dependencies, installed with the package's extras.

The core of sb3_hhp (MiniGrid, the algorithm, the oracles, the labeling app) needs none of them. The Atari
games come with ``pip install "sb3_hhp[atari]"`` (``ale-py``), the Fetch tasks with
``pip install "sb3_hhp[fetch]"`` (``gymnasium-robotics`` and ``mujoco``). Code that needs one imports it
through :func:`import_extra`, which names the extra to install when the module is missing.
"""

import contextlib
import importlib
import importlib.util
import io
from types import ModuleType
from typing import Optional

import gymnasium as gym

__all__ = ["EXTRAS", "import_extra", "missing_extra_hint", "register_fetch_envs"]

#: module -> the extra of sb3_hhp that installs it
EXTRAS = {"ale_py": "atari", "gymnasium_robotics": "fetch", "mujoco": "fetch"}


def _install_hint(extra: str) -> str:
    return f'pip install "sb3_hhp[{extra}]"'


def import_extra(module: str) -> ModuleType:
    """Import an optional dependency, or say which extra installs it.

    :param module: a module of :data:`EXTRAS` (e.g. ``"gymnasium_robotics"``)
    :return: the module
    :raises ImportError: when it is not installed, naming the extra (e.g. ``pip install "sb3_hhp[fetch]"``)
    """
    if module not in EXTRAS:
        raise ValueError(f"{module!r} is not an optional dependency of sb3_hhp: use one of {sorted(EXTRAS)}")
    try:
        return importlib.import_module(module)
    except ImportError as error:
        extra = EXTRAS[module]
        raise ImportError(
            f"{module} is not installed; it comes with the [{extra}] extra of sb3_hhp: {_install_hint(extra)}"
        ) from error


def register_fetch_envs() -> bool:
    """Register the gymnasium-robotics envs (the Fetch tasks) when the [fetch] extra is installed.

    :return: whether they are registered (False without gymnasium-robotics)
    """
    try:
        with contextlib.redirect_stderr(io.StringIO()):  # gymnasium-robotics prints a notice on Adroit envs
            robotics = import_extra("gymnasium_robotics")
    except ImportError:
        return False
    gym.register_envs(robotics)
    return True


def missing_extra_hint(env_id: str) -> Optional[str]:
    """How to install the extra that provides an env id that is not registered, for the error message.

    :param env_id: a gymnasium env id, e.g. ``"ALE/Pong-v5"`` or ``"FetchReach-v4"``
    :return: an install command such as ``pip install "sb3_hhp[atari]"``, or None when no extra provides it
    """
    if env_id.startswith("ALE/"):
        extra = "atari"
    elif env_id.startswith("Fetch"):
        extra = "fetch"
    else:
        return None
    module = next(name for name, value in EXTRAS.items() if value == extra)
    if importlib.util.find_spec(module) is not None:
        return None  # installed: the id is wrong, not the installation
    return _install_hint(extra)
