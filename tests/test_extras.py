"""Atari and Fetch are extras: the core imports without them, and code that needs one names the extra."""

import subprocess
import sys

import pytest

from sb3_hhp.extras import EXTRAS, import_extra, missing_extra_hint, register_fetch_envs

# Setting sys.modules[name] = None makes `import name` raise ImportError, as if it were not installed.
WITHOUT_EXTRAS = "import sys\n" + "".join(f"sys.modules[{name!r}] = None\n" for name in EXTRAS)


def run_without_extras(code: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-c", WITHOUT_EXTRAS + code], capture_output=True, text=True, timeout=120
    )


def test_core_imports_without_the_extras():
    code = (
        "import sb3_hhp, sb3_hhp.hhp, sb3_hhp.goals, sb3_hhp.oracles, sb3_hhp.preferences.store, sb3_hhp.train\n"
        "from sb3_hhp import HhP\n"
        "from sb3_hhp.extras import register_fetch_envs\n"
        "assert register_fetch_envs() is False\n"
        "assert not [name for name in sys.modules if name.split('.')[0] in "
        f"{sorted(EXTRAS)!r} and sys.modules[name] is not None]\n"
    )
    result = run_without_extras(code)
    assert result.returncode == 0, result.stderr


@pytest.mark.parametrize("module, extra", [("ale_py", "atari"), ("gymnasium_robotics", "fetch"), ("mujoco", "fetch")])
def test_a_missing_extra_names_what_to_install(monkeypatch, module, extra):
    monkeypatch.setitem(sys.modules, module, None)
    with pytest.raises(ImportError, match=rf'pip install "sb3_hhp\[{extra}\]"'):
        import_extra(module)


def test_hints_for_env_ids_of_missing_extras(monkeypatch):
    monkeypatch.setitem(sys.modules, "ale_py", None)
    monkeypatch.setitem(sys.modules, "gymnasium_robotics", None)
    assert missing_extra_hint("ALE/Pong-v5") == 'pip install "sb3_hhp[atari]"'
    assert missing_extra_hint("FetchReach-v4") == 'pip install "sb3_hhp[fetch]"'
    assert missing_extra_hint("MiniGrid-DoorKey-5x5-v0") is None


def test_installed_extras_import():
    pytest.importorskip("gymnasium_robotics")
    assert import_extra("gymnasium_robotics").__name__ == "gymnasium_robotics"
    assert register_fetch_envs() is True
    assert missing_extra_hint("FetchReach-v4") is None  # installed: a wrong id gets no install hint


def test_only_optional_dependencies_are_imported_as_extras():
    with pytest.raises(ValueError, match="not an optional dependency"):
        import_extra("numpy")
