from sb3_lifelong.mpo.mpo import MPO
from sb3_lifelong.mpo.policies import CnnPolicy, MlpPolicy, MultiInputPolicy

__all__ = ["MPO", "CnnPolicy", "MlpPolicy", "MultiInputPolicy"]
