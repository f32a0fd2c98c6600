from sb3_lifelong.bc.bc import BC
from sb3_lifelong.bc.policies import BCPolicy, CnnPolicy, MlpPolicy, MultiInputPolicy

__all__ = ["BC", "BCPolicy", "CnnPolicy", "MlpPolicy", "MultiInputPolicy"]
