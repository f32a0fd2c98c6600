"""
Golden schedulers and wrapper defaults (issue 66): each scheduler's law recomputed independently (NumPy draws from
the scheduler's seed, or the triangle wave by hand) and compared value by value, and the defaults of
:class:`DynamicsSchedule` that a user relies on without writing them (no appended parameters, schedule seed 0,
changes at the next episode start, the observed parameters when nothing varies, the episode counter).
"""

import zlib

import gymnasium as gym
import numpy as np
import pytest

from sb3_lifelong.envs import Cyclic, Drift, DynamicsSchedule, RandomWalk, SawWave, stage_envs

ENV_ID = "HalfCheetah-v5"
LOW, HIGH = 0.05, 20.0  # mass_scale's physical range


def bound(scheduler, name="mass_scale", low=LOW, high=HIGH, seed=0):
    scheduler.bind(name, low, high, seed)
    return scheduler


def expected_increments(law, start, std, seed, n):
    """The value after each of ``n`` increments: ``v <- law(v, N(0, std))`` with the scheduler's own generator."""
    rng = np.random.default_rng(seed)
    values, v = [start], start
    for _ in range(n):
        v = law(v, float(rng.normal(0.0, std)))
        values.append(v)
    return values


def test_a_random_walk_adds_each_draw_and_clips():
    low, high = 0.8, 1.2
    walk = bound(RandomWalk(1.0, 0.1, period=10, low=low, high=high, seed=3))
    expected = expected_increments(lambda v, d: min(max(v + d, low), high), 1.0, 0.1, 3, 60)
    assert np.random.default_rng(3).normal(0.0, 0.1) == pytest.approx(0.2040919) and expected[1] == high  # clipped
    assert any(v in (low, high) for v in expected) and len(set(expected)) > 40  # both laws (add, clip) are exercised
    for k, v in enumerate(expected):  # constant over each period, the k-th value from timestep 10 k
        assert walk.value(10 * k) == pytest.approx(v, abs=1e-12)
        assert walk.value(10 * k + 9) == pytest.approx(v, abs=1e-12)


def test_a_period_of_one_moves_from_the_first_timestep_not_before():
    walk = bound(RandomWalk(1.0, 0.1, period=1, seed=5))
    expected = expected_increments(lambda v, d: v + d, 1.0, 0.1, 5, 3)
    assert walk.value(-4) == 1.0 and walk.value(0) == 1.0  # no increment at or before timestep 0
    assert [walk.value(t) for t in range(4)] == pytest.approx(expected, abs=1e-12)


@pytest.mark.parametrize("direction", [1, -1])
def test_a_drift_moves_by_the_absolute_draw_in_its_direction(direction):
    low, high = 0.5, 1.5
    drift = bound(Drift(1.0, 0.05, direction=direction, period=2, low=low, high=high, seed=7))
    expected = expected_increments(lambda v, d: min(max(v + direction * abs(d), low), high), 1.0, 0.05, 7, 40)
    assert expected[-1] == (high if direction > 0 else low)  # reached its bound and stays
    assert [drift.value(2 * k) for k in range(41)] == pytest.approx(expected, abs=1e-12)


@pytest.mark.parametrize("direction", [1, -1])
def test_a_cycle_jumps_back_to_start_at_its_bound(direction):
    low, high, start = 0.5, 1.5, 1.0

    def law(v, d):
        v = v + direction * abs(d)
        return start if (v >= high if direction > 0 else v <= low) else v

    cyc = bound(Cyclic(start, 0.1, direction=direction, period=1, low=low, high=high, seed=11))
    expected = expected_increments(law, start, 0.1, 11, 120)
    restarts = sum(1 for a, b in zip(expected, expected[1:]) if b == start and a != start)
    assert restarts >= 3  # the law's jump is exercised, and it is not every step
    assert sum(1 for v in expected if v != start) > 60
    assert [cyc.value(t) for t in range(121)] == pytest.approx(expected, abs=1e-12)


def test_a_saw_wave_from_inside_its_range_goes_up_first_and_turns_at_the_bounds():
    saw = bound(SawWave(0.5, 1.5, half_period=100, start=0.75))
    # by hand: 0.01 per timestep, up from 0.75 to 1.5 (t = 75), down to 0.5 (t = 175), up again
    times = [0, 25, 50, 75, 100, 150, 175, 200, 275, 375]
    assert [saw.value(t) for t in times] == pytest.approx([0.75, 1.0, 1.25, 1.5, 1.25, 0.75, 0.5, 0.75, 1.5, 0.5])


def test_a_saw_wave_over_a_span_of_two_starts_where_it_is_told():
    saw = bound(SawWave(0.5, 2.5, half_period=100, start=1.0))
    # by hand: 0.02 per timestep, up from 1.0 to 2.5 (t = 75), down to 0.5 (t = 175), up again
    times = [0, 25, 75, 100, 175, 200]
    assert [saw.value(t) for t in times] == pytest.approx([1.0, 1.5, 2.5, 2.0, 0.5, 1.0])


def test_a_saw_wave_of_one_timestep_per_half_period_alternates():
    saw = bound(SawWave(0.5, 1.5, half_period=1))
    assert [saw.value(t) for t in range(5)] == pytest.approx([0.5, 1.5, 0.5, 1.5, 0.5])


def wrapped(**kwargs) -> DynamicsSchedule:
    return DynamicsSchedule(gym.make(ENV_ID), **kwargs)


def test_by_default_nothing_is_appended_to_the_observation():
    env = wrapped(stages=[{}, {"mass_scale": 2.0}], switch_at=[10])
    inner = gym.make(ENV_ID)
    assert env.observation_space == inner.observation_space
    obs, _ = env.reset(seed=0)
    assert obs.shape == inner.observation_space.shape


def test_the_default_schedule_seed_is_zero():
    env = wrapped(schedules={"mass_scale": RandomWalk(1.0, 0.1, period=1)})
    seed = zlib.crc32(b"0/mass_scale")  # the seed derived from schedule_seed 0 and the parameter's name
    assert env.schedules["mass_scale"].seed == seed == 1031447843
    expected = expected_increments(lambda v, d: min(max(v + d, LOW), HIGH), 1.0, 0.1, seed, 5)
    assert [env.schedules["mass_scale"].value(t) for t in range(6)] == pytest.approx(expected, abs=1e-12)


def test_the_first_switch_may_be_at_timestep_one():
    env = wrapped(stages=[{}, {"gravity": 5.0}], switch_at=[1], mid_episode=True)
    env.reset(seed=0)
    _, _, _, _, info = env.step(env.action_space.sample())
    assert info["stage"] == 0
    _, _, _, _, info = env.step(env.action_space.sample())
    assert info["stage"] == 1 and info["dynamics_params"]["gravity"] == 5.0


def test_with_nothing_varied_the_whole_robot_parameters_are_observed():
    env = wrapped()
    whole_robot = [
        "hip_deformation",
        "foot_scale",
        "ground_softness",
        "friction",
        "mass_scale",
        "gravity",
        "actuator_strength",
        "joint_damping",
    ]
    assert env.observed_params == whole_robot  # the limb ones (leg_motor_scale, joint_lock) are not


def test_the_episode_counter_counts_resets():
    env = wrapped()
    assert env.episodes == 0
    for n in range(1, 4):
        env.reset(seed=n)
        assert env.episodes == n


def test_a_stage_index_past_the_last_is_refused():
    env = wrapped(stages=[{}, {"gravity": 5.0}])
    with pytest.raises(ValueError, match=r"stage must be an index in \[0, 1\], got 2"):
        env.set_stage(2)


def test_set_params_waits_for_the_next_episode_unless_immediate():
    env = wrapped()
    env.reset(seed=0)
    index = env.set_params(gravity=4.0)
    assert index == 1 and env.dynamics_params["gravity"] == pytest.approx(9.81) and env.stage == 0
    env.reset(seed=1)
    assert env.dynamics_params["gravity"] == 4.0 and env.stage == 1
    env.set_params(gravity=3.0, immediate=True)
    assert env.dynamics_params["gravity"] == 3.0 and env.stage == 2


def test_stage_envs_are_in_their_stage_before_any_reset():
    envs = stage_envs(ENV_ID, [{}, {"gravity": 5.0}, {"mass_scale": 2.0}])
    assert [env.stage for env in envs.values()] == [0, 1, 2]
    assert envs["Env-B"].dynamics_params["gravity"] == 5.0
    assert envs["Env-C"].dynamics_params["mass_scale"] == 2.0
    assert envs["Env-C"].dynamics_params["gravity"] == pytest.approx(9.81)
