import csv

import gymnasium as gym
import numpy as np
import pytest
from stable_baselines3 import SAC
from testkit import pendulum_data

from sb3_lifelong import BC, CRR, MPO, LifelongReplayBuffer
from sb3_lifelong.distill import distill
from sb3_lifelong.evaluation.callbacks import MultiEnvEvalCallback


def net() -> dict:
    # a fresh dict each time: SB3 writes into the policy_kwargs it is given
    return dict(net_arch=[32, 32])


def student_kwargs(**kwargs) -> dict:
    return dict(policy_kwargs=net(), batch_size=32, seed=0, **kwargs)


def test_distill_from_mpo_logs_into_the_same_run(tmp_path):
    model = MPO("MlpPolicy", "Pendulum-v1", policy_kwargs=net(), batch_size=32, learning_starts=50, num_samples=8, seed=0)
    model.tensorboard_log = str(tmp_path)
    model.learn(250, tb_log_name="life")
    envs = {"env_a": gym.make("Pendulum-v1"), "env_b": gym.make("Pendulum-v1", g=5.0)}
    student = model.distill(CRR, total_updates=120, eval_env=envs, eval_freq=60, n_eval_episodes=1, **student_kwargs())
    assert isinstance(student, CRR)
    assert student.num_timesteps == 120
    assert student.replay_buffer is model.replay_buffer  # no copy of the lifetime buffer
    action, _ = student.predict(np.zeros((1, 3), dtype=np.float32), deterministic=True)
    assert action.shape == (1, 1) and np.all(np.abs(action) <= 2.0)
    with open(tmp_path / "life_1" / "distill" / "progress.csv") as handle:
        rows = list(csv.DictReader(handle))
    logged = [row for row in rows if row.get("eval/env_a/mean_reward")]
    assert len(logged) == 2 and all(row["eval/env_b/mean_reward"] for row in logged)


def test_distill_from_sac_with_bc_and_a_callback():
    model = SAC("MlpPolicy", "Pendulum-v1", policy_kwargs=net(), batch_size=32, learning_starts=50, seed=0)
    model.learn(150)
    callback = MultiEnvEvalCallback({"pendulum": gym.make("Pendulum-v1")}, eval_freq=40, n_eval_episodes=1)
    student = distill(model, BC, total_updates=80, callback=callback, **student_kwargs())
    assert isinstance(student, BC)
    assert [row["timesteps"] for row in callback.results] == [40, 80]


def test_distill_from_a_buffer_directory(tmp_path):
    path = tmp_path / "lifetime"
    model = MPO(
        "MlpPolicy",
        "Pendulum-v1",
        replay_buffer_class=LifelongReplayBuffer,
        replay_buffer_kwargs=dict(path=str(path), chunk_size=50),
        policy_kwargs=net(),
        batch_size=32,
        learning_starts=50,
        num_samples=8,
        seed=0,
    )
    model.learn(200)
    model.replay_buffer.flush()
    student = distill(str(path), total_updates=50, **student_kwargs())
    assert student.replay_buffer.size() == 200
    assert student.action_space.high[0] == pytest.approx(2.0)


def test_distill_needs_data():
    model = MPO("MlpPolicy", "Pendulum-v1", policy_kwargs=net())
    with pytest.raises(ValueError, match="no data"):
        model.distill(CRR, total_updates=10)


def test_model_distill_names_its_student():
    model = MPO("MlpPolicy", "Pendulum-v1", policy_kwargs=net(), learning_starts=10, batch_size=8, num_samples=4)
    model.learn(20)
    with pytest.raises(TypeError, match="offline algorithm class"):
        model.distill("CRR", total_updates=1)
    with pytest.raises(TypeError, match=r"got <class 'stable_baselines3\.sac\.sac\.SAC'>"):
        model.distill(SAC, total_updates=1)  # a class, but one that cannot learn from data alone


def two_source_data(n: int = 256, seed: int = 0) -> dict:
    """
    One-step episodes of two sources: the observation's second entry says which (0 or 1); the teacher's action is
    +0.6 in source 0 and -0.6 in source 1 (whatever the first entry), reward 1.
    """
    rng = np.random.default_rng(seed)
    sources = np.repeat([0, 1], n // 2)
    obs = np.stack([rng.uniform(-1, 1, n), sources], axis=1).astype(np.float32)
    actions = (np.where(sources == 0, 0.6, -0.6) + 0.05 * rng.normal(size=n)).reshape(-1, 1).astype(np.float32)
    return dict(
        observations=obs,
        actions=actions,
        rewards=np.ones(n, np.float32),
        next_observations=obs,
        terminals=np.ones(n, bool),
        sources=sources,
    )


def directory_digest(path) -> dict:
    import hashlib

    return {
        str(file.relative_to(path)): hashlib.sha256(file.read_bytes()).hexdigest()
        for file in sorted(path.rglob("*"))
        if file.is_file()
    }


def test_distill_leaves_a_two_source_buffer_byte_identical_and_learns_both(tmp_path):
    from gymnasium import spaces

    path = tmp_path / "lifetime"
    data = two_source_data()
    buffer = LifelongReplayBuffer.from_d4rl(
        data, spaces.Box(-1, 1, (2,)), spaces.Box(-1, 1, (1,)), normalized_actions=True, path=str(path), chunk_size=64
    )
    assert sorted(np.unique(np.array(buffer.store.read_range("sources", 0, buffer.size())))) == [0, 1]
    buffer.close()
    before = directory_digest(path)
    assert len(before) > 1
    student = distill(
        str(path),
        total_updates=300,
        policy_kwargs=dict(net_arch=[16]),
        learning_rate=3e-3,
        **{k: v for k, v in student_kwargs().items() if k != "policy_kwargs"},
    )
    student.replay_buffer.close()
    assert directory_digest(path) == before  # not a byte of the lifetime buffer changed, no file added or removed
    for source, action in ((0, 0.6), (1, -0.6)):
        obs = np.stack([np.linspace(-1, 1, 20), np.full(20, source)], axis=1).astype(np.float32)
        predicted, _ = student.predict(obs, deterministic=True)
        assert np.abs(predicted - action).max() < 0.2, (source, predicted.ravel())


def test_distill_from_a_dict_leaves_it_alone():
    """The data's arrays are read, never written: not when its actions are normalised, nor clipped to the bounds."""
    from gymnasium import spaces

    data = two_source_data(n=64)
    data["actions"][0] = 1.2  # outside the bounds: clipped in the student's copy
    copy = {key: value.copy() for key, value in data.items()}
    with pytest.warns(UserWarning, match="1 of 64 actions lie outside"):
        distill(data, BC, total_updates=20, action_space=spaces.Box(-1, 1, (1,)), **student_kwargs())
    for key, value in copy.items():
        np.testing.assert_array_equal(data[key], value, err_msg=key)


def test_distill_documents_its_arguments_once():
    """
    ``help(distill)`` and an IDE show the student's main arguments, documented there once; the pipeline below the
    algorithms takes the same ones with the same defaults, and ``model.distill`` forwards them to it by name.
    """
    import inspect

    from sb3_lifelong.common import distillation
    from sb3_lifelong.common.base import LifelongOffPolicyAlgorithm

    def parameters(function, kinds):
        return {p.name: p.default for p in inspect.signature(function).parameters.values() if p.kind in kinds}

    Parameter = inspect.Parameter
    public = inspect.signature(distill).parameters
    assert list(public)[:2] == ["source", "student_class"] and public["student_class"].default is None
    learning = parameters(distill, {Parameter.POSITIONAL_OR_KEYWORD})
    del learning["source"], learning["student_class"]
    assert parameters(distillation.distill, {Parameter.KEYWORD_ONLY}) == learning  # the same defaults
    named = parameters(distill, {Parameter.KEYWORD_ONLY})
    assert list(named) == list(distillation.NAMED_STUDENT_ARGUMENTS) and set(named.values()) == {None}
    for name in ("beta", "advantage_transform", "batch_size", "learning_rate", "seed", "eval_env", "loss"):
        assert name in {**learning, **named}
    for name in [*learning, *named, "source", "student_class", "student_kwargs"]:
        assert f":param {name}:" in distill.__doc__, f"distill does not document {name}"
    method = inspect.signature(LifelongOffPolicyAlgorithm.distill).parameters
    assert list(method) == ["self", "student_class", "kwargs"] and method["kwargs"].kind is Parameter.VAR_KEYWORD
    assert ":func:`sb3_lifelong.distill.distill`" in LifelongOffPolicyAlgorithm.distill.__doc__


def test_model_distill_leaves_none_to_the_student():
    """A named argument left at None takes the student's default, through the method as through the function."""
    model = MPO("MlpPolicy", "Pendulum-v1", policy_kwargs=net(), learning_starts=10, batch_size=8, num_samples=4)
    model.learn(20)
    student = model.distill(BC, total_updates=2, beta=None, batch_size=None, seed=0, policy_kwargs=net())
    assert isinstance(student, BC) and student.batch_size == BC("MlpPolicy", "Pendulum-v1").batch_size


def test_distill_forwards_the_named_arguments_and_refuses_foreign_ones():
    data, spaces = pendulum_data(200), dict(action_space=gym.make("Pendulum-v1").action_space)
    student = distill(
        data, CRR, total_updates=2, beta=3.0, max_weight=5.0, batch_size=16, seed=0, policy_kwargs=net(), **spaces
    )
    assert (student.beta, student.max_weight, student.batch_size) == (3.0, 5.0, 16)
    student = distill(data, BC, total_updates=2, loss="mse", batch_size=16, seed=0, policy_kwargs=net(), **spaces)
    assert student.loss == "mse"
    with pytest.raises(TypeError, match="BC takes no argument 'beta'"):
        distill(data, BC, total_updates=2, beta=3.0)
    with pytest.raises(TypeError, match="CRR takes no argument 'betta'"):
        distill(data, CRR, total_updates=2, betta=3.0)
    # the constructors' gradient_steps (updates after each rollout) is not the distillation's number of updates
    with pytest.raises(TypeError, match=r"total_updates gradient updates \(got gradient_steps=500000"):
        distill(data, CRR, gradient_steps=500_000, **spaces)
    teacher = MPO("MlpPolicy", "Pendulum-v1", learning_starts=1_000, policy_kwargs=net())
    teacher.learn(20)
    with pytest.raises(TypeError, match=r"pass total_updates=\.\.\. instead"):
        teacher.distill(CRR, gradient_steps=10)
    with pytest.raises(TypeError, match="'gradient_steps'"):
        CRR.from_offline_data(data, **spaces).learn_offline(gradient_steps=2)  # type: ignore[call-arg]


def test_the_student_sees_what_the_teacher_saw():
    """
    ``policy`` left at None: a ``CnnPolicy`` teacher (MPO's, or SAC's) gets a ``CnnPolicy`` student, an ``MlpPolicy``
    teacher an ``MlpPolicy`` one; data alone get the policy their observation space calls for. A named policy wins.
    """
    from stable_baselines3.common.envs import FakeImageEnv
    from stable_baselines3.common.torch_layers import FlattenExtractor, NatureCNN

    from sb3_lifelong.bc import CnnPolicy as BCCnnPolicy
    from sb3_lifelong.common.distillation import teacher_policy_alias
    from sb3_lifelong.crr import CnnPolicy as CRRCnnPolicy
    from sb3_lifelong.crr import MlpPolicy as CRRMlpPolicy

    small_cnn = dict(net_arch=[16], features_extractor_kwargs=dict(features_dim=16))
    env = FakeImageEnv(screen_height=36, screen_width=36, n_channels=1, discrete=False)
    teacher = MPO(
        "CnnPolicy",
        env,
        learning_starts=40,
        batch_size=8,
        num_samples=4,
        policy_kwargs=small_cnn,
        seed=0,
        replay_buffer_class=LifelongReplayBuffer,
    )
    teacher.learn(50)
    student = teacher.distill(CRR, total_updates=2, batch_size=8, seed=0, policy_kwargs=small_cnn)
    assert type(student.policy) is CRRCnnPolicy and isinstance(student.actor.features_extractor, NatureCNN)
    assert student.observation_space == teacher.observation_space  # channel-first, as the teacher's buffer holds it
    student = teacher.distill(BC, total_updates=2, batch_size=8, seed=0, policy_kwargs=small_cnn)
    assert type(student.policy) is BCCnnPolicy
    named = teacher.distill(CRR, policy="MlpPolicy", total_updates=2, batch_size=8, seed=0, policy_kwargs=net())
    assert type(named.policy) is CRRMlpPolicy and isinstance(named.actor.features_extractor, FlattenExtractor)
    # the buffer alone: its channel-first uint8 images call for a CNN
    from_data = distill(teacher.replay_buffer, BC, total_updates=2, batch_size=8, seed=0, policy_kwargs=small_cnn)
    assert type(from_data.policy) is BCCnnPolicy

    assert teacher_policy_alias(SAC("CnnPolicy", env, buffer_size=10), CRR) == "CnnPolicy"
    assert teacher_policy_alias(MPO("MlpPolicy", "Pendulum-v1"), CRR) == "MlpPolicy"
    assert teacher_policy_alias(teacher, BC) == "CnnPolicy"

    class OwnPolicy(BCCnnPolicy):
        pass

    # a policy class of the teacher's own: no name to follow (the data's observation space decides)
    assert teacher_policy_alias(BC(OwnPolicy, env, buffer_size=10, policy_kwargs=small_cnn), CRR) is None


def test_policy_alias_for_an_observation_space():
    from gymnasium import spaces

    from sb3_lifelong.common.policies import policy_alias_for

    image = spaces.Box(0, 255, (3, 36, 36), np.uint8)
    assert policy_alias_for(image) == "CnnPolicy"
    assert policy_alias_for(spaces.Dict({"img": image, "vec": spaces.Box(-1, 1, (2,))})) == "MultiInputPolicy"
    assert policy_alias_for(spaces.Box(-1, 1, (3,), np.float32)) == "MlpPolicy"
    assert policy_alias_for(spaces.Box(0, 255, (36, 36, 3), np.uint8)) == "MlpPolicy"  # channel-last: a CNN would misread it
    assert policy_alias_for(spaces.Box(0.0, 1.0, (3, 36, 36), np.float32)) == "MlpPolicy"  # not an image to SB3


def test_from_offline_data_picks_the_policy_of_its_data_when_given_none():
    from gymnasium import spaces

    from sb3_lifelong.bc import MultiInputPolicy as BCMultiInputPolicy
    from sb3_lifelong.crr import MlpPolicy as CRRMlpPolicy

    model = CRR.from_offline_data(pendulum_data(50), policy=None, action_space=gym.make("Pendulum-v1").action_space)
    assert type(model.policy) is CRRMlpPolicy
    observation_space = spaces.Dict({"pos": spaces.Box(-1, 1, (3,), np.float32), "mode": spaces.Discrete(2)})
    action_space = spaces.Box(-1, 1, (2,), np.float32)
    buffer = LifelongReplayBuffer(0, observation_space, action_space)
    rng = np.random.default_rng(0)
    for _ in range(20):
        obs = {"pos": rng.uniform(-1, 1, (1, 3)).astype(np.float32), "mode": rng.integers(0, 2, (1, 1))}
        buffer.add(obs, obs, rng.uniform(-1, 1, (1, 2)).astype(np.float32), np.zeros(1), np.zeros(1), [{}])
    model = BC.from_offline_data(buffer, policy=None, policy_kwargs=net())
    assert type(model.policy) is BCMultiInputPolicy
    model.learn_offline(2)
    assert model.num_timesteps == 2
