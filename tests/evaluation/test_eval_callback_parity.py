"""MultiEnvEvalCallback as SB3's EvalCallback: the best model, evaluations.npz, child callbacks, VecNormalize statistics."""

import gymnasium as gym
import numpy as np
import pytest
from stable_baselines3.common.callbacks import BaseCallback, StopTrainingOnRewardThreshold
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

from sb3_lifelong import MPO
from sb3_lifelong.evaluation.callbacks import MultiEnvEvalCallback

SMALL = dict(policy_kwargs=dict(net_arch=[32, 32]), batch_size=32, learning_starts=50, num_samples=8)


class RecordBest(BaseCallback):
    """Records its parent's best score each time it is called."""

    def __init__(self) -> None:
        super().__init__()
        self.seen: list[float] = []

    def _on_step(self) -> bool:
        assert self.parent is not None
        self.seen.append(self.parent.best_mean_reward)
        return True


def test_best_model_and_evaluations_npz(tmp_path):
    envs = {"Env-A": gym.make("Pendulum-v1"), "Env-B": gym.make("Pendulum-v1", g=5.0)}
    on_best, after_eval = RecordBest(), RecordBest()
    callback = MultiEnvEvalCallback(
        envs,
        eval_freq=100,
        n_eval_episodes=2,
        seed=0,
        best_model_save_path=tmp_path / "best",
        evaluations_dir=tmp_path / "logs",
        callback_on_new_best=on_best,
        callback_after_eval=after_eval,
    )
    model = MPO("MlpPolicy", "Pendulum-v1", seed=0, **SMALL)
    model.learn(400, callback=callback)

    with np.load(tmp_path / "logs" / "evaluations.npz") as npz:
        assert list(npz["timesteps"]) == [100, 200, 300, 400]
        assert list(npz["env_names"]) == ["Env-A", "Env-B"]
        assert npz["results"].shape == npz["ep_lengths"].shape == (4, 2, 2)
        assert (npz["ep_lengths"] == 200).all()
        results = npz["results"]
    logged = [row["mean_reward"] for row in callback.results]
    np.testing.assert_allclose(results.mean(axis=2).reshape(-1), logged)
    scores = results.mean(axis=(1, 2))  # eval/mean_over_envs of each evaluation
    records = [score for index, score in enumerate(scores) if score > max(scores[:index], default=-np.inf)]
    assert on_best.seen == pytest.approx(records)  # called exactly on the new bests, after the best was updated
    assert after_eval.seen == pytest.approx(list(np.maximum.accumulate(scores)))
    assert callback.best_mean_reward == pytest.approx(scores.max())
    assert callback.last_mean_reward == pytest.approx(scores[-1])
    best = MPO.load(tmp_path / "best" / "best_model.zip")
    assert best.num_timesteps == 100 * (int(np.argmax(scores)) + 1)


def test_a_child_callback_stops_training():
    envs = {"Env-A": gym.make("Pendulum-v1")}
    stop = StopTrainingOnRewardThreshold(reward_threshold=-1e9)  # any score stops
    callback = MultiEnvEvalCallback(envs, eval_freq=100, n_eval_episodes=1, callback_on_new_best=stop)
    model = MPO("MlpPolicy", "Pendulum-v1", seed=0, **SMALL)
    model.learn(500, callback=callback)
    assert model.num_timesteps == 100


def _evaluated_with(obs_rms, seed: int, normalize: bool, model) -> float:
    env = DummyVecEnv([lambda: Monitor(gym.make("Pendulum-v1"))])
    if normalize:
        env = VecNormalize(env, training=False, norm_reward=False)
        env.obs_rms = obs_rms
    env.seed(seed)
    rewards, _ = evaluate_policy(model, env, n_eval_episodes=1, deterministic=True)
    return float(rewards)


def test_vec_normalize_statistics_reach_the_evaluation_envs():
    """A model trained on VecNormalize observations is evaluated on normalised observations, with its statistics."""
    training = VecNormalize(make_vec_env("Pendulum-v1", seed=0), norm_obs=True, norm_reward=False)
    callback = MultiEnvEvalCallback({"Env-A": gym.make("Pendulum-v1")}, eval_freq=10_000, n_eval_episodes=1, seed=5)
    model = MPO("MlpPolicy", training, seed=0, **SMALL)
    model.learn(200, callback=callback)  # evaluates nothing
    statistics = training.obs_rms.copy()
    means = callback.evaluate()
    wrapped = callback._normalized_envs["Env-A"]
    assert not wrapped.training and not wrapped.norm_reward
    np.testing.assert_array_equal(wrapped.obs_rms.mean, statistics.mean)  # the evaluation did not update them
    assert wrapped.obs_rms is not training.obs_rms
    seed = callback.episode_seed(0)  # the seed of this evaluation's episodes (drawn from 5 and the timestep)
    assert means["Env-A"] == pytest.approx(_evaluated_with(statistics, seed, True, model))
    assert means["Env-A"] != pytest.approx(_evaluated_with(statistics, seed, False, model))
