"""sb3_hhp: Hierarchical learning from human preferences and curiosity (HhP) for Stable-Baselines3."""

import os

with open(os.path.join(os.path.dirname(__file__), "version.txt")) as file_handler:
    __version__ = file_handler.read().strip()


def __getattr__(name: str):
    # HhP is imported lazily so that `import sb3_hhp` stays light (and registers nothing global).
    if name in ("HhP", "PAPER_KWARGS"):
        from sb3_hhp import hhp

        return getattr(hhp, name)
    if name == "HierarchicalEnv":
        from sb3_hhp.hierarchy import HierarchicalEnv

        return HierarchicalEnv
    raise AttributeError(f"module 'sb3_hhp' has no attribute {name!r}")


__all__ = ["HhP", "HierarchicalEnv", "PAPER_KWARGS", "__version__"]
