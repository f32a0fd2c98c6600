"""DynamicsSchedule: stage switching by global timestep, schedulers, manual control, errors, env checkers."""

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env as gym_check_env
from stable_baselines3 import SAC
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.env_checker import check_env as sb3_check_env
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.vec_env import SubprocVecEnv

from sb3_lifelong import MPO
from sb3_lifelong.core.contract import SYNC_TIMESTEP_METHOD
from sb3_lifelong.envs import (
    Constant,
    Cyclic,
    Drift,
    DynamicsSchedule,
    LinearRamp,
    RandomWalk,
    SawWave,
    UniformPerEpisode,
)

ENV_ID = "HalfCheetah-v5"  # fastest Gymnasium MuJoCo env


def wrapped(**kwargs) -> DynamicsSchedule:
    return DynamicsSchedule(gym.make(ENV_ID), **kwargs)


class StageRecorder(BaseCallback):
    """Records (timestep before the step, stage, gravity) of every collected transition."""

    def __init__(self) -> None:
        super().__init__()
        self.records: list = []

    def _on_step(self) -> bool:
        t = self.model.num_timesteps - self.training_env.num_envs
        for info in self.locals["infos"]:
            self.records.append((t, info["stage"], info["dynamics_params"]["gravity"]))
        return True


@pytest.mark.parametrize("n_envs,switch", [(1, 101), (2, 100), (2, 101)])
def test_switch_at_exact_model_timestep_across_learn_calls(n_envs: int, switch: int) -> None:
    vec_env = make_vec_env(
        ENV_ID,
        n_envs=n_envs,
        seed=0,
        wrapper_class=DynamicsSchedule,
        wrapper_kwargs=dict(stages=[{}, {"gravity": 5.0}], switch_at=[switch], n_envs=n_envs, mid_episode=True),
    )
    # SAC that never trains (learning_starts beyond the run): only the collection loop is exercised
    model = SAC("MlpPolicy", vec_env, learning_starts=10_000, buffer_size=1_000, seed=0, policy_kwargs=dict(net_arch=[8]))
    recorder = StageRecorder()
    model.learn(80, callback=recorder)
    model.learn(80, callback=recorder, reset_num_timesteps=False)
    assert model.num_timesteps >= 160
    for t, stage, gravity in recorder.records:
        expected = int(t >= switch)
        assert stage == expected, (t, stage)
        assert gravity == (5.0 if expected else 9.81)
    first_new = min(t for t, stage, _ in recorder.records if stage == 1)
    assert first_new == switch + (-switch) % n_envs  # first model timestep >= switch reachable with n_envs
    # the wrappers count exactly like SB3
    assert vec_env.get_attr("timestep") == [model.num_timesteps] * n_envs


def test_schedule_learns_the_model_timestep_from_learn() -> None:
    # neither n_envs nor start_timestep is passed: learn() tells the wrappers the model's timestep and n_envs
    assert hasattr(DynamicsSchedule, SYNC_TIMESTEP_METHOD)
    vec_env = make_vec_env(
        ENV_ID,
        n_envs=2,
        seed=0,
        wrapper_class=DynamicsSchedule,
        wrapper_kwargs=dict(stages=[{}, {"gravity": 5.0}], switch_at=[101], mid_episode=True),
    )
    # this package's algorithm (SB3's own do not tell the env), which never trains: only collection is exercised
    model = MPO("MlpPolicy", vec_env, learning_starts=10_000, buffer_size=1_000, seed=0, policy_kwargs=dict(net_arch=[8]))
    recorder = StageRecorder()
    model.learn(80, callback=recorder)
    model.num_timesteps = 1_000  # e.g. a continued run: the schedule follows the model, not the caller's arithmetic
    model.learn(10, callback=recorder, reset_num_timesteps=False)
    assert [r[1] for r in recorder.records] == [int(t >= 101) for t, _, _ in recorder.records]
    assert recorder.records[-1][:2] == (1_008, 1)
    assert vec_env.get_attr("timestep") == [model.num_timesteps] * 2
    model.learn(4, callback=recorder)  # reset_num_timesteps=True: the schedule starts again too
    assert recorder.records[-1][:2] == (2, 0)


def test_switch_applies_at_episode_start_by_default() -> None:
    env = gym.wrappers.TimeLimit(gym.make(ENV_ID).unwrapped, max_episode_steps=30)
    env = DynamicsSchedule(env, stages=[{}, {"gravity": 3.0}], switch_at=[45])
    _, info = env.reset(seed=0)
    assert info["stage"] == 0
    stages = []
    for _ in range(90):
        _, _, terminated, truncated, info = env.step(env.action_space.sample())
        stages.append(info["stage"])
        if terminated or truncated:
            _, info = env.reset()
            stages.append(("reset", info["stage"]))
    # the switch is due at 45 (mid episode) and happens at the reset after step 60
    assert stages[:61] == [0] * 30 + [("reset", 0)] + [0] * 30
    assert stages[61] == ("reset", 1)
    assert env.unwrapped.model.opt.gravity[2] == pytest.approx(-3.0)


def test_subproc_vec_env_same_schedule() -> None:
    vec_env = make_vec_env(
        ENV_ID,
        n_envs=2,
        seed=0,
        vec_env_cls=SubprocVecEnv,
        wrapper_class=DynamicsSchedule,
        wrapper_kwargs=dict(
            stages=[{}, {"friction": 0.2}],
            switch_at=[10],
            schedules={"mass_scale": RandomWalk(1.0, 0.05, period=2, low=0.5, high=1.5)},
            n_envs=2,
            mid_episode=True,
        ),
    )
    try:
        vec_env.reset()
        seen = []
        for _ in range(12):
            _, _, _, infos = vec_env.step(np.zeros((2, 6)))
            assert infos[0]["dynamics_params"] == infos[1]["dynamics_params"]
            assert infos[0]["stage"] == infos[1]["stage"]
            seen.append(infos[0]["stage"])
        assert seen == [0] * 5 + [1] * 7
        assert len({p for p in vec_env.get_attr("timestep")}) == 1
    finally:
        vec_env.close()


def test_info_and_append_params() -> None:
    env = wrapped(stages=[{"hip_deformation": 0.25, "gravity": 9.81 * 0.5}], append_params=True)
    assert env.observation_space.shape == (17 + 2,)
    assert env.observed_params == ["gravity", "hip_deformation"]
    obs, info = env.reset(seed=1)
    assert info["stage"] == 0
    assert set(info["dynamics_params"]) == set(env.supported_params)
    assert info["dynamics_params"]["hip_deformation"] == 0.25
    assert obs[-1] == pytest.approx(0.25 / 0.5)  # (value - nominal) / obs_scale
    assert obs[-2] == pytest.approx(-0.5)
    obs, _, _, _, info = env.step(env.action_space.sample())
    assert obs.shape == (19,) and info["dynamics_params"]["gravity"] == pytest.approx(4.905)


@pytest.mark.parametrize(
    "kwargs",
    [
        dict(stages=[{}, {"foot_scale": 1.3}], switch_at=[3], append_params=True, mid_episode=True),
        dict(schedules={"friction": UniformPerEpisode(0.2, 1.0)}, append_params=True),
        # a change under way makes two seeded episodes differ (the env is non-stationary on purpose), which
        # Gymnasium's determinism check rejects: ramp after the checker's few steps
        dict(schedules={"gravity": LinearRamp(9.81, 5.0, 10_000, 20_000)}, mid_episode=True),
    ],
)
def test_env_checkers_on_wrapped_env(kwargs) -> None:
    gym_check_env(wrapped(**kwargs), skip_render_check=True)
    sb3_check_env(wrapped(**kwargs), warn=True)


def test_set_stage_set_params_resume() -> None:
    env = wrapped(stages=[{}, "hip_0.3"], switch_at=[1000])
    env.reset(seed=0)
    env.set_stage(1)
    assert env.stage == 0  # applied at the next episode start
    _, info = env.reset()
    assert info["stage"] == 1 and info["dynamics_params"]["hip_deformation"] == 0.3
    index = env.set_params({"friction": 0.3}, immediate=True)
    assert index == 2 and env.stage == 2
    assert env.dynamics_params["friction"] == 0.3 and env.dynamics_params["hip_deformation"] == 0.0
    assert env.set_params(hip_deformation=0.3) == 1  # an equal setting reuses its stage
    env.resume_schedule()
    _, info = env.reset()
    assert info["stage"] == 0 and info["dynamics_params"] == env.nominal_params
    env.set_timestep(2000)
    _, info = env.reset()
    assert info["stage"] == 1


def test_schedulers_follow_definitions() -> None:
    ramp = LinearRamp(1.0, 2.0, begin=100, finish=200)
    ramp.bind("mass_scale", 0.05, 20.0, 0)
    assert [ramp.value(t) for t in (0, 100, 150, 200, 500)] == [1.0, 1.0, 1.5, 2.0, 2.0]

    walk = RandomWalk(1.0, 0.1, period=10, low=0.8, high=1.2, seed=3)
    walk.bind("mass_scale", 0.05, 20.0, 0)
    values = [walk.value(t) for t in range(0, 2000)]
    assert values[:10] == [1.0] * 10 and len(set(values[10:20])) == 1  # changes only every period
    steps = np.diff(values[::10])
    assert np.all((np.array(values) >= 0.8) & (np.array(values) <= 1.2))
    assert np.std(steps[np.abs(steps) > 0]) < 0.15
    again = RandomWalk(1.0, 0.1, period=10, low=0.8, high=1.2, seed=3)
    again.bind("mass_scale", 0.05, 20.0, 99)
    assert [again.value(t) for t in range(0, 2000, 7)] == values[::7]  # same seed, same walk, any query order
    assert walk.value(15) == values[15]  # going back in time replays

    up = Drift(1.0, 0.05, direction=1, period=1, high=1.5, seed=0)
    up.bind("mass_scale", 0.05, 20.0, 0)
    drift = [up.value(t) for t in range(200)]
    assert np.all(np.diff(drift) >= 0) and drift[-1] == 1.5

    cyc = Cyclic(1.0, 0.05, direction=-1, period=1, low=0.5, seed=0)
    cyc.bind("mass_scale", 0.05, 20.0, 0)
    cycle = np.array([cyc.value(t) for t in range(300)])
    assert cycle.min() > 0.5 and np.sum(np.diff(cycle) > 0) >= 2  # went back to start more than once
    assert np.all(cycle[1:][np.diff(cycle) > 0] == 1.0)

    saw = SawWave(0.5, 1.5, half_period=100)
    saw.bind("mass_scale", 0.05, 20.0, 0)
    assert [saw.value(t) for t in (0, 50, 100, 150, 200, 250)] == pytest.approx([0.5, 1.0, 1.5, 1.0, 0.5, 1.0])

    const = Constant(0.7)
    const.bind("friction", 0.0, 10.0, 0)
    assert const.value(12345) == 0.7


def test_uniform_per_episode_reproducible_and_in_bounds() -> None:
    def draws(seed: int) -> list:
        env = wrapped(schedules={"friction": UniformPerEpisode(0.2, 0.6)})
        out = [env.reset(seed=seed)[1]["dynamics_params"]["friction"]]
        out += [env.reset()[1]["dynamics_params"]["friction"] for _ in range(5)]
        return out

    a, b, c = draws(0), draws(0), draws(1)
    assert a == b and a != c
    assert all(0.2 <= v <= 0.6 for v in a) and len(set(a)) == 6


def test_continuous_schedule_mid_episode_reaches_physics() -> None:
    env = wrapped(schedules={"gravity": LinearRamp(9.81, 1.0, 0, 100)}, mid_episode=True)
    env.reset(seed=0)
    for t in range(120):
        _, _, _, _, info = env.step(np.zeros(6))
        expected = 9.81 + (1.0 - 9.81) * min(t / 100, 1.0)
        assert info["dynamics_params"]["gravity"] == pytest.approx(expected)
        assert -env.unwrapped.model.opt.gravity[2] == pytest.approx(expected)
        assert info["stage"] == 0


def test_mid_episode_change_keeps_the_robot_state() -> None:
    env = DynamicsSchedule(gym.make("Walker2d-v5"))
    env.reset(seed=0)
    for _ in range(20):
        env.step(env.action_space.sample())
    data = env.unwrapped.data
    qpos, qvel, time = data.qpos.copy(), data.qvel.copy(), data.time
    for setting in ({"mass_scale": 1.3}, {"foot_scale": 1.4}, {}):  # field edits and a recompile
        env.set_params(setting, immediate=True)
        np.testing.assert_array_equal(data.qpos, qpos)
        np.testing.assert_array_equal(data.qvel, qvel)
        assert data.time == time


@pytest.mark.parametrize(
    "kwargs,match",
    [
        (
            dict(stages=[{"hip_deformaton": 0.3}]),
            r"unknown dynamics parameter 'hip_deformaton'.*Allowed: hip_deformation \[rad\]",
        ),
        (dict(stages=[{"foot_scale": -1.0}]), r"foot_scale=-1.0 x nominal is outside its physical range"),
        (dict(stages=[{"ground_softness": 0.001}]), r"ground_softness.*outside.*\[0.02"),  # below 2 time steps
        (dict(stages=[{"gravity": float("nan")}]), r"gravity=nan"),
        (dict(stages=[{}, {}, {}], switch_at=[200, 100]), r"strictly increasing.*out of order"),
        (dict(stages=[{}, {}, {}], switch_at=[100]), r"one global timestep per stage"),
        (dict(stages=[{}, {}], switch_at=[0]), r"strictly increasing positive"),
        (dict(stages=["hip_9"]), r"unknown named stage 'hip_9'"),
        (dict(schedules={"mass": RandomWalk(1.0, 0.1)}), r"unknown dynamics parameter 'mass'.*mass_scale"),
        (dict(schedules={"friction": RandomWalk(1.0, 0.1, low=-1.0)}), r"bounds \[-1.0, .*physical range"),
        (dict(schedules={"friction": Cyclic(1.0, 0.1, high=1.0)}), r"start must differ"),
        (dict(n_envs=0), r"n_envs must be >= 1"),
    ],
)
def test_clear_errors(kwargs, match) -> None:
    with pytest.raises(ValueError, match=match):
        wrapped(**kwargs)


def test_errors_for_unsupported_envs_and_manual_calls() -> None:
    with pytest.raises(TypeError, match="not a MuJoCo env"):
        DynamicsSchedule(gym.make("CartPole-v1"))
    env = wrapped()
    with pytest.raises(ValueError, match=r"stage must be an index in \[0, 0\]"):
        env.set_stage(3)
    with pytest.raises(ValueError, match="unknown dynamics parameter 'grav'"):
        env.set_params(grav=1.0)


def test_stage_envs_pins_one_copy_per_stage():
    from sb3_lifelong.envs import stage_envs

    stages = [{}, {"hip_deformation": 0.3}, "default"]
    envs = stage_envs("Hopper-v5", stages, append_params=True)
    assert list(envs) == ["Env-A", "Env-B", "Env-C"]
    for index, env in enumerate(envs.values()):
        obs, info = env.reset(seed=0)
        assert info["stage"] == index and obs.shape == env.observation_space.shape
        for _ in range(3):
            assert env.step(env.action_space.sample())[-1]["stage"] == index
    assert envs["Env-B"].dynamics_params["hip_deformation"] == pytest.approx(0.3)
    assert list(stage_envs("Hopper-v5", stages[:2], names=["old", "new"])) == ["old", "new"]
    # monitored: SB3's evaluate_policy takes a copy as it is, quietly
    import warnings

    from stable_baselines3.common.evaluation import evaluate_policy

    class Still:
        def predict(self, obs, state=None, episode_start=None, deterministic=True):
            return np.zeros((len(obs), 3), dtype=np.float32), None

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        rewards, lengths = evaluate_policy(Still(), envs["Env-B"], n_eval_episodes=1, return_episode_rewards=True)
    assert len(rewards) == len(lengths) == 1 and lengths[0] > 0
    with pytest.raises(ValueError, match="switch_at"):
        stage_envs("Hopper-v5", stages, switch_at=[10, 20])
    with pytest.raises(ValueError, match="one distinct name per stage"):
        stage_envs("Hopper-v5", stages, names=["a", "a", "b"])


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(stages=[{"friction": True}]), "friction must be a real number"),
        (dict(stages=[{"foot_scale": "2.0"}]), "foot_scale must be a real number"),
        (dict(start_timestep=-1), "start_timestep must be a non-negative integer"),
        (dict(start_timestep=2.5), "start_timestep must be a non-negative integer"),
        (dict(start_timestep=True), "start_timestep must be a non-negative integer"),
    ],
)
def test_a_schedule_refuses_values_of_the_wrong_type_or_sign(kwargs, message):
    with pytest.raises(ValueError, match=message):
        DynamicsSchedule(gym.make("Hopper-v5"), **kwargs)


def test_one_name_per_environment():
    """The data of stage i, in the buffer, has the name of stage i's evaluation copy: the same name in every log."""
    from sb3_lifelong import LifelongReplayBuffer
    from sb3_lifelong.envs import stage_envs

    stages = [{}, {"hip_deformation": 0.3}]
    env = DynamicsSchedule(gym.make("Hopper-v5"), stages=stages)
    buffer = LifelongReplayBuffer(0, env.observation_space, env.action_space)
    for stage in range(2):
        env.set_stage(stage, immediate=True)
        obs, _ = env.reset(seed=stage)
        for _ in range(5):
            action = env.action_space.sample()
            next_obs, reward, terminated, _truncated, info = env.step(action)
            buffer.add(obs[None], next_obs[None], action[None], np.array([reward]), np.array([terminated]), [info])
            obs = next_obs
    assert list(buffer.source_counts(by_name=True)) == list(stage_envs("Hopper-v5", stages)) == ["Env-A", "Env-B"]


def test_a_saw_wave_of_no_half_period_is_refused():
    from sb3_lifelong.envs import SawWave

    with pytest.raises(ValueError, match="half_period must be >= 1"):
        DynamicsSchedule(gym.make("HalfCheetah-v5"), schedules={"mass_scale": SawWave(0.5, 1.5, half_period=0)})


def test_switch_at_of_the_wrong_length_says_how_many_it_needs():
    with pytest.raises(ValueError, match=r"2 values for 3 stages, got 1"):
        DynamicsSchedule(gym.make("HalfCheetah-v5"), stages=[{}, {"mass_scale": 1.5}, {"mass_scale": 2.0}], switch_at=[100])


# ------------------------------------------------------------------------------------- each check at its boundary
@pytest.mark.parametrize(
    "scheduler, match",
    [
        (LinearRamp(1.0, 1.5, begin=100, finish=100), r"LinearRamp for friction: need 0 <= begin < finish, got begin=100"),
        (LinearRamp(1.0, 1.5, begin=-1, finish=100), r"need 0 <= begin < finish, got begin=-1, finish=100"),
        (RandomWalk(1.0, 0.1, period=0), r"RandomWalk for friction: need period >= 1 and std >= 0"),
        (RandomWalk(1.0, -0.1), r"need period >= 1 and std >= 0"),
        (RandomWalk(5.0, 0.1, low=0.5, high=2.0), r"RandomWalk for friction: start=5.0 outside \[0.5, 2.0\]"),
        (RandomWalk(0.49, 0.1, low=0.5, high=2.0), r"start=0.49 outside \[0.5, 2.0\]"),
        (LinearRamp(-1.0, 1.5, begin=0, finish=10), r"LinearRamp for friction: bounds \[-1.0, 1.5\] must satisfy 0 <= low"),
        (LinearRamp(1.5, 11.0, begin=0, finish=10), r"bounds \[1.5, 11.0\] must satisfy 0 <= low < high <= 10"),
        (LinearRamp(11.0, 11.0, begin=0, finish=10), r"LinearRamp for friction: start=11.0 outside \[0.0, 10.0\]"),
        (UniformPerEpisode(0.5, 0.5), r"UniformPerEpisode for friction: bounds \[0.5, 0.5\] must satisfy 0 <= low < high"),
    ],
)
def test_scheduler_checks_name_the_parameter_and_the_value(scheduler, match) -> None:
    with pytest.raises(ValueError, match=match):
        wrapped(schedules={"friction": scheduler})


def test_scheduler_checks_accept_their_boundaries() -> None:
    ramp = LinearRamp(1.0, 1.5, begin=0, finish=1)
    walk = RandomWalk(0.5, 0.0, period=1, low=0.5, high=2.0)  # start at low, no noise, a step every timestep
    env = wrapped(schedules={"friction": ramp, "mass_scale": walk})
    assert (ramp.value(0), ramp.value(1), ramp.value(10)) == (1.0, 1.5, 1.5)
    assert [walk.value(t) for t in (0, 1, 5, 50)] == [0.5, 0.5, 0.5, 0.5]
    assert (ramp.low, ramp.high) == (1.0, 1.5)  # a ramp's bounds are its two ends (the physical range: a flat one's)
    env.close()
    down, flat = LinearRamp(1.5, 0.0, begin=0, finish=1), LinearRamp(10.0, 10.0, begin=0, finish=1)
    wrapped(schedules={"friction": down, "gravity": flat}).close()
    assert (down.low, down.high, flat.low, flat.high) == (0.0, 1.5, 0.0, 100.0)


def test_the_incremental_schedulers_step_every_thousand_timesteps_by_default() -> None:
    assert RandomWalk(1.0, 0.1).period == Drift(1.0, 0.1).period == 1000


def test_a_constant_ramp_takes_the_parameters_physical_range() -> None:
    ramp = LinearRamp(1.2, 1.2, begin=0, finish=10)
    env = wrapped(schedules={"friction": ramp})
    assert (ramp.low, ramp.high) == env.editor.valid_range("friction")
    assert ramp.value(0) == ramp.value(5) == ramp.value(100) == 1.2
    env.close()


def test_drift_direction_is_plus_or_minus_one() -> None:
    with pytest.raises(ValueError, match=r"direction must be \+1 or -1, got 0"):
        Drift(1.0, 0.1, direction=0)
    for direction in (1, -1):
        drift = Drift(1.0, 0.1, direction=direction, period=1, low=0.5, high=1.5, seed=0)
        env = wrapped(schedules={"friction": drift})
        values = [drift.value(t) for t in range(6)]
        assert all(direction * (b - a) >= 0 for a, b in zip(values, values[1:])) and values[-1] != values[0]
        env.close()


@pytest.mark.parametrize(
    "kwargs, error, match",
    [
        (dict(stages=[]), ValueError, r"stages must hold at least one setting \(use \[\{\}\] for the nominal robot\)"),
        (dict(schedules={"friction": 1.0}), TypeError, r"schedules\['friction'\] must be a Scheduler .* got 1.0"),
        (dict(stages=[{}, 5]), TypeError, r"stages\[1\] must be a dict of parameter values or a named stage, got 5"),
    ],
)
def test_wrong_kinds_are_named(kwargs, error, match) -> None:
    with pytest.raises(error, match=match):
        wrapped(**kwargs)


def test_append_params_needs_a_flat_box() -> None:
    flat = DynamicsSchedule(gym.make(ENV_ID), stages=[{}, {"friction": 1.5}], append_params=True)
    assert flat.observation_space.shape == (17 + 1,)
    flat.close()
    with pytest.raises(ValueError, match=r"append_params needs a flat Box observation space, got Box\(.*\(1, 17\)"):
        DynamicsSchedule(gym.wrappers.ReshapeObservation(gym.make(ENV_ID), (1, 17)), append_params=True)


def test_the_timestep_hook_refuses_no_envs_and_stages_are_copies() -> None:
    env = wrapped(stages=[{}, {"friction": 1.5}], switch_at=[100])
    sync = getattr(env, SYNC_TIMESTEP_METHOD)
    with pytest.raises(ValueError, match=r"n_envs must be >= 1, got 0"):
        sync(10, 0)
    sync(100, 1)
    assert env.timestep == 100 and env.stage == 0  # the change waits for the next episode (mid_episode=False)
    env.reset(seed=0)
    assert env.stage == 1
    stages = env.stages
    stages[1]["friction"] = 9.0
    assert env.stages[1] == {"friction": 1.5}  # a copy: the env's stages are unchanged
    index = env.set_params({"friction": 1.2})
    assert index == 2 and env.stages == [{}, {"friction": 1.5}, {"friction": 1.2}]
    env.close()
