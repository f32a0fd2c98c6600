from sb3_lifelong.bc.bc import BC
from sb3_lifelong.bc.policies import BCPolicy, MlpPolicy, MultiInputPolicy

__all__ = ["BC", "BCPolicy", "MlpPolicy", "MultiInputPolicy"]
