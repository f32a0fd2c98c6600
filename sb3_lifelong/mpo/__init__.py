from sb3_lifelong.mpo.mpo import MPO
from sb3_lifelong.mpo.policies import MlpPolicy, MultiInputPolicy

__all__ = ["MPO", "MlpPolicy", "MultiInputPolicy"]
