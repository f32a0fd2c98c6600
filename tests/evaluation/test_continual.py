"""The continual-learning metrics (Continual World / GEM terms) of a return matrix, and the callback that keeps it."""

import json
import math

import gymnasium as gym
import numpy as np
import pytest
from stable_baselines3.common.vec_env import DummyVecEnv

from sb3_lifelong import MPO
from sb3_lifelong.envs import DynamicsSchedule, stage_envs
from sb3_lifelong.evaluation.callbacks import MultiEnvEvalCallback
from sb3_lifelong.evaluation.continual import ContinualMetricsCallback, continual_metrics, random_policy_returns


def test_metrics_by_hand_on_three_stages():
    returns = [[80.0, 10.0, 30.0], [40.0, 90.0, 50.0], [20.0, 70.0, 100.0]]
    random = [0.0, 10.0, 0.0]
    reference = [100.0, 110.0, 100.0]
    out = continual_metrics(returns, random, reference)
    s = np.array([[0.8, 0.0, 0.3], [0.4, 0.8, 0.5], [0.2, 0.6, 1.0]])
    np.testing.assert_allclose(out["scores"], s)
    assert out["average_performance"] == pytest.approx(0.6)
    assert out["forgetting"] == {0: pytest.approx(0.6), 1: pytest.approx(0.2)}  # s[j][j] - s[last][j]
    assert out["forgetting_mean"] == pytest.approx(0.4)
    assert out["backward_transfer"] == pytest.approx(-0.4)
    assert out["forward_transfer"] == pytest.approx((0.0 + 0.5) / 2)  # s[0][1], s[1][2]


def test_metrics_signs_follow_what_happened():
    """Remembering gives zero forgetting; improving on an old environment later is negative forgetting (positive BWT)."""
    kept = continual_metrics([[100.0, 0.0], [100.0, 100.0]], [0.0, 0.0])
    assert kept["forgetting_mean"] == 0.0 and kept["average_performance"] == 1.0
    improved = continual_metrics([[50.0, 0.0], [100.0, 100.0]], [0.0, 0.0])  # default reference: the best seen
    assert improved["forgetting"][0] == pytest.approx(-0.5) and improved["backward_transfer"] == pytest.approx(0.5)
    lost = continual_metrics([[100.0, 0.0], [10.0, 100.0]], [0.0, 0.0])
    assert lost["forgetting"][0] == pytest.approx(0.9)


def test_metrics_before_a_second_stage_and_bad_input():
    first = continual_metrics([[60.0, 20.0]], [0.0, 0.0], [100.0, 100.0])
    assert math.isnan(first["forgetting_mean"]) and first["forward_transfer"] == pytest.approx(0.2)
    assert first["average_performance"] == pytest.approx(0.4)
    with pytest.raises(ValueError, match="reference must exceed the random"):
        continual_metrics([[0.0, 5.0]], [1.0, 0.0])
    with pytest.raises(ValueError, match="one value per environment"):
        continual_metrics([[1.0, 2.0]], [0.0])
    with pytest.raises(ValueError, match="stage i trains in environment i"):
        continual_metrics([[1.0], [2.0]], [0.0])


def test_callback_keeps_the_matrix_and_logs(tmp_path):
    stages = [{}, {"leg_motor_scale": -1.0}]
    env = DynamicsSchedule(gym.make("Hopper-v5", max_episode_steps=50), stages=stages, switch_at=[300], append_params=True)
    envs = stage_envs("Hopper-v5", stages, ["Env-A", "Env-B"], dict(max_episode_steps=50), append_params=True)
    floor = {"Env-A": -1e3, "Env-B": -1e3}  # below any return here: the scores are defined however little was learnt
    metrics = ContinualMetricsCallback(stage_ends=[300], random_returns=floor, log_path=tmp_path / "continual.json")
    evaluation = MultiEnvEvalCallback(envs, eval_freq=150, n_eval_episodes=2, seed=0, same_episodes=True,
                                      callback_after_eval=metrics)  # fmt: skip
    model = MPO("MlpPolicy", env, learning_starts=100, batch_size=16, num_samples=4, policy_kwargs=dict(net_arch=[16]),
                seed=0, tensorboard_log=str(tmp_path / "tb"))  # fmt: skip
    model.learn(600, callback=evaluation)
    record = json.loads((tmp_path / "continual.json").read_text())
    by_time = {(r["timesteps"], r["env"]): r["mean_reward"] for r in evaluation.results}
    assert record["row_timesteps"] == [300, 600]  # the last evaluation of each stage
    assert record["returns"] == [[by_time[(t, "Env-A")], by_time[(t, "Env-B")]] for t in (300, 600)]
    assert record["random"] == [-1e3, -1e3] and record["normalisation"].startswith("s[i][j]")
    again = continual_metrics(record["returns"], record["random"])
    for key in ("average_performance", "forward_transfer", "backward_transfer"):
        assert record[key] == pytest.approx(again[key])
    assert set(record["forgetting"]) == {"Env-A"}
    tags = set()
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    for events in (tmp_path / "tb").rglob("events.out.tfevents.*"):
        accumulator = EventAccumulator(str(events))
        accumulator.Reload()
        tags |= set(accumulator.Tags()["scalars"])
    assert {"continual/average_performance", "continual/forgetting/Env-A", "continual/backward_transfer"} <= tags
    assert {"continual/R/after_Env-A/Env-A", "continual/R/after_Env-B/Env-A"} <= tags  # rows named as the envs
    # a random policy's returns, seeded like the evaluations: the same twice
    metrics.random_episodes = 2
    first, second = metrics.measure_random(), metrics.measure_random()
    assert first == second and set(first) == {"Env-A", "Env-B"} and all(np.isfinite(list(first.values())))


def test_callback_refuses_what_it_cannot_read():
    with pytest.raises(ValueError, match="strictly increasing"):
        ContinualMetricsCallback(stage_ends=[300, 200])
    envs = stage_envs("Hopper-v5", [{}, {"joint_lock": 1.0}, {"joint_lock": 0.5}], ["A", "B", "C"], append_params=True)
    with pytest.raises(ValueError, match="1 stage ends for 3 evaluated environments"):
        MultiEnvEvalCallback(envs, callback_after_eval=ContinualMetricsCallback(stage_ends=[10])).init_callback(
            MPO("MlpPolicy", "Pendulum-v1", learning_starts=10)
        )
    standalone = ContinualMetricsCallback(stage_ends=[10])
    with pytest.raises(TypeError, match="callback_after_eval of a MultiEnvEvalCallback"):
        standalone.init_callback(MPO("MlpPolicy", "Pendulum-v1", learning_starts=10))


def test_an_environment_not_evaluated_before_its_stage_leaves_forward_transfer_undefined():
    # Env-B was not evaluated at the end of stage 0 (a Stage 1 run alone, adopted later): everything else is defined
    metrics = continual_metrics([[100.0, math.nan], [60.0, 120.0]], [0.0, 20.0])
    assert metrics["average_performance"] == pytest.approx((0.6 + 1.0) / 2)
    assert metrics["forgetting"] == {0: pytest.approx(0.4)} and math.isnan(metrics["forward_transfer"])
    # an environment must be measured at the end of its own stage and later
    for missing in ([[math.nan, 5.0], [60.0, 120.0]], [[100.0, 5.0], [math.nan, 120.0]], [[100.0, 5.0], [60.0, math.nan]]):
        with pytest.raises(ValueError, match="finite in every environment at the end of its own stage"):
            continual_metrics(missing, [0.0, 0.0])


def test_random_policy_returns_follow_a_seeded_random_policy_episode_by_episode():
    def by_hand(env_seed: int, action_seed: int, episodes: int) -> float:
        env = gym.make("Pendulum-v1", max_episode_steps=50)
        env.action_space.seed(action_seed)
        totals, seed = [], env_seed
        for _ in range(episodes):
            env.reset(seed=seed)
            seed, total, ended = None, 0.0, False
            while not ended:
                _, reward, terminated, truncated, _ = env.step(env.action_space.sample())
                total, ended = total + float(reward), terminated or truncated
            totals.append(total)
        return float(np.mean(totals))

    envs = {"A": gym.make("Pendulum-v1", max_episode_steps=50), "B": gym.make("Pendulum-v1", max_episode_steps=50)}
    measured = random_policy_returns(envs, 3, env_seeds=[5, 6], action_seeds=[7, 8])
    # a VecEnv keeps rewards as float32, so equal to float32 rounding
    assert measured == pytest.approx({"A": by_hand(5, 7, 3), "B": by_hand(6, 8, 3)}, rel=1e-6)
    # a VecEnv of the same environment plays the same episodes; another action seed plays others
    vec = DummyVecEnv([lambda: gym.make("Pendulum-v1", max_episode_steps=50)])
    assert random_policy_returns({"A": vec}, 3, env_seeds=[5], action_seeds=[7]) == pytest.approx({"A": measured["A"]})
    assert random_policy_returns({"A": vec}, 3, env_seeds=[5], action_seeds=[9])["A"] != pytest.approx(measured["A"])
    # several sub-environments: the first episodes to end count, no more
    pair = DummyVecEnv([lambda: gym.make("Pendulum-v1", max_episode_steps=50)] * 2)
    assert np.isfinite(random_policy_returns({"A": pair}, 3, env_seeds=[5], action_seeds=[7])["A"])
    with pytest.raises(ValueError, match="env_seeds has 1 seeds for 2 environments"):
        random_policy_returns(envs, 1, env_seeds=[5])
    with pytest.raises(ValueError, match="episodes must be >= 1"):
        random_policy_returns(envs, 0)
