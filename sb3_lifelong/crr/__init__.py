from sb3_lifelong.crr.crr import CRR
from sb3_lifelong.crr.policies import CRRPolicy, MlpPolicy, MultiInputPolicy

__all__ = ["CRR", "CRRPolicy", "MlpPolicy", "MultiInputPolicy"]
