from sb3_hhp.hhp.hhp import PAPER_KWARGS, HhP
from sb3_hhp.hhp.policies import CnnPolicy, MlpPolicy, MultiInputPolicy

__all__ = ["CnnPolicy", "HhP", "MlpPolicy", "MultiInputPolicy", "PAPER_KWARGS"]
