from sb3_lifelong.mpo.mpo import MPO
from sb3_lifelong.mpo.policies import CnnPolicy, MlpPolicy, MultiInputPolicy
from sb3_lifelong.mpo.settings import PolicyLossConfig

__all__ = ["MPO", "CnnPolicy", "MlpPolicy", "MultiInputPolicy", "PolicyLossConfig"]
