from sb3_lifelong.crr.crr import CRR
from sb3_lifelong.crr.policies import CnnPolicy, CRRPolicy, MlpPolicy, MultiInputPolicy

__all__ = ["CRR", "CRRPolicy", "CnnPolicy", "MlpPolicy", "MultiInputPolicy"]
