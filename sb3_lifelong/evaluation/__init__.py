"""
Measuring a model while it trains, in any algorithm: evaluation in several named environments, the critic's values
per data source against the Monte-Carlo returns of the stored data, the ``train/`` values as CSV, and forgetting and
transfer in the continual-learning field's terms.
"""

from sb3_lifelong.evaluation.callbacks import (
    EVAL_SEED_OFFSET,
    MultiEnvEvalCallback,
    SourceQCallback,
    TrainLogCallback,
    make_eval_envs,
)
from sb3_lifelong.evaluation.continual import ContinualMetricsCallback, continual_metrics, random_policy_returns
from sb3_lifelong.evaluation.overestimation import MonteCarloProbe, discounted_returns, monte_carlo_horizon

__all__ = [
    "EVAL_SEED_OFFSET",
    "ContinualMetricsCallback",
    "MonteCarloProbe",
    "MultiEnvEvalCallback",
    "SourceQCallback",
    "TrainLogCallback",
    "continual_metrics",
    "discounted_returns",
    "make_eval_envs",
    "monte_carlo_horizon",
    "random_policy_returns",
]
