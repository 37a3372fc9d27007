from sb3_hhp.hhp.arguments import PAPER_KWARGS
from sb3_hhp.hhp.hhp import HhP
from sb3_hhp.hhp.policies import CnnPolicy, MlpPolicy, MultiInputPolicy

__all__ = ["CnnPolicy", "HhP", "MlpPolicy", "MultiInputPolicy", "PAPER_KWARGS"]
