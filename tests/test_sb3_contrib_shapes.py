"""
sb3-contrib's own tests of its algorithms, ``tests/test_save_load.py`` and ``tests/test_dict_env.py``, with every
algorithm of this package in the model list (MPO, CRR, BC: all three learn online through SB3's ``learn``, as
sb3-contrib's do; CRR and BC also learn offline, tested elsewhere), and the ``CnnPolicy`` each has, as SB3's SAC does:
images through the lifetime buffer (``LifelongReplayBuffer``, in memory and on disk), stored as ``uint8``.

Shaped like sb3-contrib's tests (same steps, same checks), with tiny networks and few steps, and stricter where the
package promises more: parameters equal exactly after a load, predictions equal exactly on the same device.
"""

import json
import os
from collections import OrderedDict
from copy import deepcopy

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.envs import FakeImageEnv, IdentityEnvBox, SimpleMultiObsEnv
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.torch_layers import CombinedExtractor, NatureCNN
from stable_baselines3.common.utils import get_device
from stable_baselines3.common.vec_env import DummyVecEnv, VecFrameStack, VecNormalize, VecTransposeImage

from sb3_lifelong import BC, CRR, MPO, LifelongReplayBuffer
from sb3_lifelong.bc import CnnPolicy as BCCnnPolicy
from sb3_lifelong.crr import CnnPolicy as CRRCnnPolicy
from sb3_lifelong.mpo import CnnPolicy as MPOCnnPolicy

MODEL_LIST = [MPO, CRR, BC]
CNN_POLICIES = {MPO: MPOCnnPolicy, CRR: CRRCnnPolicy, BC: BCCnnPolicy}


def rand_like(tensor: th.Tensor) -> th.Tensor:
    if th.is_floating_point(tensor):
        return th.rand_like(tensor)
    # int tensor
    return th.randint_like(tensor, high=10)


def fast(model_class, **kwargs) -> dict:
    """The model's arguments for a short test: MPO scores 4 sampled actions per state instead of 20."""
    if model_class is MPO:
        kwargs.setdefault("num_samples", 4)
    return dict(batch_size=32, seed=0, **kwargs)


def parameters_equal(first: dict, second: dict) -> None:
    """Every tensor of every object (optimizers skipped: their layout is not comparable tensor by tensor) is equal."""
    assert first.keys() == second.keys()
    for object_name in first:
        if "optim" in object_name:
            continue
        assert first[object_name].keys() == second[object_name].keys(), object_name
        for key, value in first[object_name].items():
            assert th.equal(value.cpu(), second[object_name][key].cpu()), f"{object_name}.{key} differs"


# --- sb3-contrib's tests/test_save_load.py ---------------------------------------------------------------------------


@pytest.mark.parametrize("model_class", MODEL_LIST)
def test_save_load(tmp_path, model_class):
    """``save`` and ``load`` give the same parameters and actions; ``get_parameters`` / ``set_parameters`` work."""
    env = DummyVecEnv([lambda: IdentityEnvBox(-10, 10)])
    model = model_class("MlpPolicy", env, policy_kwargs=dict(net_arch=[16]), **fast(model_class, learning_starts=50))
    model.learn(total_timesteps=100)
    assert model._n_updates == 50

    env.reset()
    observations = np.concatenate([env.step([env.action_space.sample()])[0] for _ in range(10)], axis=0)

    # deepcopy to avoid referencing to tensors we are about to modify
    original_params = deepcopy(model.get_parameters())
    expected_objects = {"policy", "actor.optimizer"} | ({"critic.optimizer"} if model_class is not BC else set())
    assert expected_objects <= set(original_params)

    # invalid object names throw errors
    invalid_object_params = deepcopy(original_params)
    invalid_object_params["I_should_not_be_a_valid_object"] = "and_I_am_an_invalid_tensor"
    with pytest.raises(ValueError):
        model.set_parameters(invalid_object_params, exact_match=True)
    with pytest.raises(ValueError):
        model.set_parameters(invalid_object_params, exact_match=False)

    # exact_match catches a missing object
    missing_object_params = {k: v for k, v in list(original_params.items())[:-1]}
    with pytest.raises(ValueError):
        model.set_parameters(missing_object_params, exact_match=True)

    # exact_match catches a missing tensor in a state dict (torch's strict load_state_dict)
    missing_state_dict_tensor_params = {
        object_name: dict(list(params.items())[:-1]) for object_name, params in original_params.items()
    }
    with pytest.raises(RuntimeError):
        model.set_parameters(missing_state_dict_tensor_params, exact_match=True)

    # the parameters do change, all but the last of each state dict, which was not given
    random_params = {}
    for object_name, params in original_params.items():
        if "optim" in object_name:  # custom layout
            random_params[object_name] = params
        else:
            random_params[object_name] = OrderedDict((name, rand_like(param)) for name, param in list(params.items())[:-1])
    model.set_parameters(random_params, exact_match=False)
    new_params = model.get_parameters()
    for object_name in original_params:
        if "optim" in object_name:
            continue
        last_key = list(original_params[object_name].keys())[-1]
        for k in original_params[object_name]:
            changed = not th.equal(original_params[object_name][k], new_params[object_name][k])
            assert changed == (k != last_key), f"{object_name}.{k}"

    params = deepcopy(new_params)
    selected_actions, _ = model.predict(observations, deterministic=True)
    model.save(tmp_path / "test_save.zip")
    del model

    devices = ["cpu", "auto"] + (["cuda"] if th.cuda.is_available() else [])
    for device in devices:
        model = model_class.load(str(tmp_path / "test_save.zip"), env=env, device=device)
        assert model.device.type == get_device(device).type
        assert model.policy.device.type == get_device(device).type
        new_params = model.get_parameters()
        for object_name in new_params:
            if "optim" in object_name:
                continue
            for key in params[object_name]:
                assert new_params[object_name][key].device.type == get_device(device).type
        parameters_equal(params, new_params)

        new_selected_actions, _ = model.predict(observations, deterministic=True)
        if model.device.type == "cpu":
            np.testing.assert_array_equal(selected_actions, new_selected_actions)
        else:
            np.testing.assert_allclose(selected_actions, new_selected_actions, atol=1e-4)

        # learn still works
        model.learn(total_timesteps=60, reset_num_timesteps=False)
        assert model.num_timesteps == 160
        del model


@pytest.mark.parametrize("model_class", MODEL_LIST)
def test_set_env(model_class):
    """``set_env`` with a VecEnv or a plain env: the model learns on the new one."""
    env = DummyVecEnv([lambda: IdentityEnvBox(-10, 10)])
    env2 = DummyVecEnv([lambda: IdentityEnvBox(-10, 10)])
    env3 = IdentityEnvBox(-10, 10)

    model = model_class("MlpPolicy", env, policy_kwargs=dict(net_arch=[16]), **fast(model_class, learning_starts=20))
    model.learn(total_timesteps=50)
    updates = model._n_updates
    assert updates == 30

    model.set_env(env2)
    assert model.get_env() is env2
    model.learn(total_timesteps=50)  # num_timesteps starts again from 0: 30 updates again
    assert model._n_updates == 2 * updates and model.replay_buffer.size() == 100

    model.set_env(env3)  # wrapped, as SB3 wraps it
    assert model.get_env().envs[0].unwrapped is env3
    model.learn(total_timesteps=50)
    assert model._n_updates == 3 * updates and model.replay_buffer.size() == 150 and model.num_timesteps == 50


@pytest.mark.parametrize("model_class", MODEL_LIST)
def test_exclude_include_saved_params(tmp_path, model_class):
    """``save(exclude=...)`` leaves a parameter out; ``include`` puts it back."""
    env = DummyVecEnv([lambda: IdentityEnvBox(-10, 10)])
    # verbose=2 is not the default
    model = model_class("MlpPolicy", env, policy_kwargs=dict(net_arch=[16]), verbose=2)

    model.save(tmp_path / "test_save", exclude=["verbose"])
    del model
    model = model_class.load(str(tmp_path / "test_save.zip"))
    assert model.verbose != 2

    model.verbose = 2
    model.save(tmp_path / "test_save", exclude=["verbose"], include=["verbose"])
    del model
    model = model_class.load(str(tmp_path / "test_save.zip"))
    assert model.verbose == 2
    os.remove(tmp_path / "test_save.zip")


@pytest.mark.parametrize("model_class", MODEL_LIST)
@pytest.mark.parametrize("buffer_class", [ReplayBuffer, LifelongReplayBuffer])
def test_save_load_replay_buffer(tmp_path, model_class, buffer_class):
    """``save_replay_buffer`` then ``load_replay_buffer`` give the same transitions, and learning goes on with them."""
    path = tmp_path / "logs" / "replay_buffer.pkl"
    model = model_class(
        "MlpPolicy",
        IdentityEnvBox(-10, 10),
        buffer_size=1000,
        replay_buffer_class=buffer_class,
        policy_kwargs=dict(net_arch=[16]),
        **fast(model_class, learning_starts=50),
    )
    model.learn(100)
    old_replay_buffer = deepcopy(model.replay_buffer)
    model.save_replay_buffer(path)
    model.replay_buffer = None
    model.load_replay_buffer(path)
    assert type(model.replay_buffer) is buffer_class and model.replay_buffer.size() == 100

    if buffer_class is ReplayBuffer:
        for name in ("observations", "actions", "rewards", "dones", "timeouts"):
            np.testing.assert_array_equal(getattr(old_replay_buffer, name), getattr(model.replay_buffer, name), name)
        infos = [[{"TimeLimit.truncated": truncated}] for truncated in old_replay_buffer.timeouts]
        # extending the replay buffer
        model.replay_buffer.extend(
            old_replay_buffer.observations,
            old_replay_buffer.observations,
            old_replay_buffer.actions,
            old_replay_buffer.rewards,
            old_replay_buffer.dones,
            infos,
        )
        assert model.replay_buffer.full
    else:
        for name in ("observations", "next_observations", "actions", "rewards", "flags"):
            np.testing.assert_array_equal(
                old_replay_buffer.read_range(name, 0, 100), model.replay_buffer.read_range(name, 0, 100), name
            )
        model.learn(20, reset_num_timesteps=False)  # collection goes on into the loaded buffer
        assert model.replay_buffer.size() == 120


@pytest.mark.parametrize("model_class", MODEL_LIST)
@pytest.mark.parametrize("policy_str", ["MlpPolicy", "CnnPolicy"])
def test_save_load_policy(tmp_path, model_class, policy_str):
    """The policy alone, and its actor alone, saved and loaded: the same parameters, the same actions."""
    if policy_str == "MlpPolicy":
        env = IdentityEnvBox(-10, 10)
        kwargs = dict(learning_starts=50, policy_kwargs=dict(net_arch=[16]))
    else:
        env = FakeImageEnv(screen_height=40, screen_width=40, n_channels=2, discrete=False)
        # a small buffer and small features (SB3 allocates the buffer whole)
        kwargs = dict(
            buffer_size=250,
            learning_starts=80,
            policy_kwargs=dict(net_arch=[16], features_extractor_kwargs=dict(features_dim=32)),
        )
    env = DummyVecEnv([lambda: env])
    model = model_class(policy_str, env, **fast(model_class, **kwargs))
    model.learn(total_timesteps=100)

    env.reset()
    observations = np.concatenate([env.step([env.action_space.sample()])[0] for _ in range(10)], axis=0)

    policy = model.policy
    policy_class = policy.__class__
    if policy_str == "CnnPolicy":
        assert policy_class is CNN_POLICIES[model_class]
        assert isinstance(policy.actor.features_extractor, NatureCNN) and policy.actor.features_extractor.features_dim == 32
    actor = policy.actor
    actor_class = actor.__class__

    params = deepcopy(policy.state_dict())
    random_params = {param_name: rand_like(param) for param_name, param in params.items()}
    policy.load_state_dict(random_params)
    new_params = policy.state_dict()
    for k in params:
        assert not th.allclose(params[k], new_params[k]), "Parameters did not change as expected."
    params = deepcopy(new_params)

    selected_actions, _ = policy.predict(observations, deterministic=True)
    selected_actions_actor, _ = actor.predict(observations, deterministic=True)
    np.testing.assert_array_equal(selected_actions_actor, selected_actions)  # the policy acts with its actor

    policy.save(tmp_path / "policy.pkl")
    actor.save(tmp_path / "actor.pkl")
    device = policy.device
    del policy, actor

    policy = policy_class.load(tmp_path / "policy.pkl").to(device)
    actor = actor_class.load(tmp_path / "actor.pkl")
    new_params = policy.state_dict()
    assert new_params.keys() == params.keys()
    for key in params:
        assert th.equal(params[key], new_params[key]), f"{key}: policy parameters not the same after save and load"

    new_selected_actions, _ = policy.predict(observations, deterministic=True)
    np.testing.assert_array_equal(selected_actions, new_selected_actions)
    new_selected_actions_actor, _ = actor.predict(observations, deterministic=True)
    np.testing.assert_array_equal(selected_actions_actor, new_selected_actions_actor)


# --- sb3-contrib's tests/test_dict_env.py ----------------------------------------------------------------------------


class DummyDictEnv(gym.Env):
    """Custom Environment for testing purposes only: an image, a vector and a discrete observation."""

    metadata = {"render_modes": ["human"]}

    def __init__(self, channel_last=False, nested_dict_obs=False, vec_only=False, size=36):
        super().__init__()
        self.action_space = spaces.Box(low=-1, high=1, shape=(2,), dtype=np.float32)
        obs_shape = (size, size, 1) if channel_last else (1, size, size)
        self.observation_space = spaces.Dict(
            {
                "img": spaces.Box(low=0, high=255, shape=obs_shape, dtype=np.uint8),
                "vec": spaces.Box(low=-1, high=1, shape=(2,), dtype=np.float32),
                "discrete": spaces.Discrete(4),
            }
        )
        # for checking consistency with a normal MlpPolicy
        if vec_only:
            self.observation_space = spaces.Dict({"vec": spaces.Box(low=-1, high=1, shape=(2,), dtype=np.float32)})
        if nested_dict_obs:
            self.observation_space.spaces["nested-dict"] = spaces.Dict({"nested-dict-discrete": spaces.Discrete(4)})
        self._obs = self.observation_space.sample()

    def reset(self, *, seed=None, options=None):
        if seed is not None:
            self.observation_space.seed(seed)
        self._obs = self.observation_space.sample()
        return self._obs, {}

    def step(self, action):
        reward = -float(np.sum((np.asarray(action) - self._obs["vec"]) ** 2))  # the action to take is in "vec"
        self._obs = self.observation_space.sample()
        return self._obs, reward, False, False, {}

    def render(self):
        pass


def dict_kwargs(model_class, **policy_kwargs) -> dict:
    # a small buffer, small features, few updates (as sb3-contrib's)
    return fast(
        model_class, buffer_size=250, train_freq=8, gradient_steps=1, policy_kwargs=dict(net_arch=[32], **policy_kwargs)
    )


@pytest.mark.parametrize(
    "model_class, extra", [(model_class, {}) for model_class in MODEL_LIST] + [(MPO, dict(policy_on_next_obs=False))]
)
def test_consistency(model_class, extra):
    """
    Dict observations with a vector only and the flattened observations give the same networks, hence the same
    actions, before and after learning (exactly: the same computations). MPO also with ``policy_on_next_obs=False``,
    whose target pass joins the observations and the next observations of a Dict batch key by key.
    """
    dict_env = gym.wrappers.TimeLimit(DummyDictEnv(vec_only=True), 100)
    env = gym.wrappers.FlattenObservation(dict_env)
    obs, _ = dict_env.reset(seed=10)

    dict_model = model_class("MultiInputPolicy", dict_env, gamma=0.5, **dict_kwargs(model_class), **extra)
    assert isinstance(dict_model.policy.actor.features_extractor, CombinedExtractor)
    action_before_learning_1, _ = dict_model.predict(obs, deterministic=True)
    dict_model.learn(total_timesteps=160)

    normal_model = model_class("MlpPolicy", env, gamma=0.5, **dict_kwargs(model_class), **extra)
    action_before_learning_2, _ = normal_model.predict(obs["vec"], deterministic=True)
    normal_model.learn(total_timesteps=160)
    assert dict_model._n_updates == normal_model._n_updates == 8  # after each rollout of 8 steps past 100: 104, ..., 160

    action_1, _ = dict_model.predict(obs, deterministic=True)
    action_2, _ = normal_model.predict(obs["vec"], deterministic=True)
    np.testing.assert_array_equal(action_before_learning_1, action_before_learning_2)
    np.testing.assert_array_equal(action_1, action_2)
    assert not np.array_equal(action_1, action_before_learning_1)  # learning changed the policy


@pytest.mark.parametrize("model_class", MODEL_LIST)
@pytest.mark.parametrize("channel_last", [False, True])
def test_dict_spaces(model_class, channel_last):
    """Mixed observations (image, vector, discrete) through ``MultiInputPolicy``: learn, then evaluate."""
    env = gym.wrappers.TimeLimit(DummyDictEnv(channel_last=channel_last), 100)
    model = model_class(
        "MultiInputPolicy", env, gamma=0.5, **dict_kwargs(model_class, features_extractor_kwargs=dict(cnn_output_dim=16))
    )
    # SB3 transposes the channel-last image, as for any algorithm
    assert isinstance(model.get_env(), VecTransposeImage) == channel_last
    assert model.observation_space["img"].shape == (1, 36, 36)
    assert set(model.policy.actor.features_extractor.extractors) == {"img", "vec", "discrete"}
    model.learn(total_timesteps=120)
    assert model._n_updates == 3
    assert model.replay_buffer.observations["img"].dtype == np.uint8
    evaluate_policy(model, env, n_eval_episodes=1, warn=False)


@pytest.mark.parametrize("model_class", MODEL_LIST)
@pytest.mark.parametrize("channel_last", [False, True])
def test_dict_vec_framestack(model_class, channel_last):
    """Dict observations through a ``VecEnvWrapper`` (``VecFrameStack``) with ``MultiInputPolicy``."""
    channels_order = {"vec": None, "img": "last" if channel_last else "first"}
    env = DummyVecEnv([lambda: SimpleMultiObsEnv(random_start=True, discrete_actions=False, channel_last=channel_last)])
    env = VecFrameStack(env, n_stack=3, channels_order=channels_order)
    model = model_class(
        "MultiInputPolicy", env, gamma=0.5, **dict_kwargs(model_class, features_extractor_kwargs=dict(cnn_output_dim=16))
    )
    assert model.observation_space["img"].shape == (3, 64, 64)
    assert model.observation_space["vec"].shape == (15,)
    model.learn(total_timesteps=120)
    assert model._n_updates == 3
    evaluate_policy(model, env, n_eval_episodes=1, warn=False)


@pytest.mark.parametrize("model_class", MODEL_LIST)
def test_vec_normalize(model_class):
    """Dict observations through ``VecNormalize`` of one key with ``MultiInputPolicy``."""
    env = DummyVecEnv([lambda: gym.wrappers.TimeLimit(DummyDictEnv(), 100)])
    env = VecNormalize(env, norm_obs_keys=["vec"])
    model = model_class(
        "MultiInputPolicy", env, gamma=0.5, **dict_kwargs(model_class, features_extractor_kwargs=dict(cnn_output_dim=16))
    )
    model.learn(total_timesteps=120)
    assert model._n_updates == 3 and env.obs_rms["vec"].count > 100  # the statistics follow the collection
    evaluate_policy(model, env, n_eval_episodes=1, warn=False)


@pytest.mark.parametrize("model_class", MODEL_LIST)
def test_dict_observations_need_multi_input_policy(model_class):
    """As in SB3: a Dict space with ``CnnPolicy`` (or ``MlpPolicy``) is refused, naming ``MultiInputPolicy``."""
    for policy in ("CnnPolicy", "MlpPolicy"):
        with pytest.raises(ValueError, match="MultiInputPolicy"):
            model_class(policy, DummyDictEnv())


# --- CnnPolicy: images through the lifetime buffer -------------------------------------------------------------------


@pytest.mark.parametrize("on_disk", [False, True])
def test_mpo_cnn_policy_learns_from_images_in_the_lifetime_buffer(tmp_path, on_disk):
    """
    MPO's ``CnnPolicy`` on a channel-last ``uint8`` image env, the transitions in a ``LifelongReplayBuffer`` (in
    memory, or in a directory): the images are stored as ``uint8`` (one byte a pixel), sampled as ``uint8`` tensors
    that the policy divides by 255, and every network (the actor's CNN and the critic's) is trained.
    """
    env = FakeImageEnv(screen_height=36, screen_width=36, n_channels=3, discrete=False)
    buffer_kwargs = dict(path=str(tmp_path / "buffer")) if on_disk else {}
    model = MPO(
        "CnnPolicy",
        env,
        learning_starts=50,
        train_freq=2,
        target_update_interval=10,
        replay_buffer_class=LifelongReplayBuffer,
        replay_buffer_kwargs=buffer_kwargs,
        policy_kwargs=dict(net_arch=[16], features_extractor_kwargs=dict(features_dim=16)),
        **fast(MPO),
    )
    assert isinstance(model.policy, MPOCnnPolicy) and model.policy.normalize_images
    assert model.observation_space == spaces.Box(0, 255, (3, 36, 36), np.uint8)  # SB3 transposes to channel-first
    extractors = {name: getattr(model.policy, name).features_extractor for name in ("actor", "critic", "critic_target")}
    assert all(isinstance(cnn, NatureCNN) for cnn in extractors.values())
    assert len({id(cnn) for cnn in extractors.values()}) == 3  # not shared (share_features_extractor=False)
    initial = {name: deepcopy(cnn.state_dict()) for name, cnn in extractors.items()}

    model.learn(200)
    assert model._n_updates == 75

    buffer = model.replay_buffer
    assert isinstance(buffer, LifelongReplayBuffer) and buffer.size() == 200
    stored = buffer.read_range("observations", 0, 200)
    assert stored.dtype == np.uint8 and stored.shape == (200, 3, 36, 36)
    samples = buffer.sample(8)
    assert samples.observations.dtype == th.uint8 and samples.observations.shape == (8, 3, 36, 36)
    assert samples.next_observations.dtype == th.uint8
    if on_disk:
        buffer.flush()
        manifest = json.loads((tmp_path / "buffer" / "manifest.json").read_text())
        assert manifest["fields"]["observations"] == {"dtype": "|u1", "shape": [3, 36, 36]}
        assert os.path.getsize(tmp_path / "buffer" / "observations.bin") == 200 * 3 * 36 * 36  # one byte a pixel

    for name, cnn in extractors.items():  # the CNNs were trained (the target's by its copies of the critic)
        changed = [key for key, value in cnn.state_dict().items() if not th.equal(value, initial[name][key])]
        assert changed, f"the {name}'s CNN did not change"
        assert all(th.isfinite(value).all() for value in cnn.state_dict().values())
    action, _ = model.predict(env.observation_space.sample(), deterministic=True)  # an (H, W, C) image, as the env's
    assert action.shape == (5,) and np.all(np.abs(action) <= 1)


@pytest.mark.parametrize("model_class", [CRR, BC])
def test_cnn_policy_of_crr_and_bc_trains_on_images_in_the_lifetime_buffer(model_class):
    """CRR's and BC's ``CnnPolicy`` train on images from a ``LifelongReplayBuffer``, the actor's CNN included."""
    env = FakeImageEnv(screen_height=36, screen_width=36, n_channels=1, discrete=False)
    model = model_class(
        "CnnPolicy",
        env,
        learning_starts=50,
        train_freq=4,
        replay_buffer_class=LifelongReplayBuffer,
        policy_kwargs=dict(net_arch=[16], features_extractor_kwargs=dict(features_dim=16)),
        **fast(model_class),
    )
    assert isinstance(model.policy, CNN_POLICIES[model_class])
    initial = deepcopy(model.policy.actor.features_extractor.state_dict())
    model.learn(100)
    assert model._n_updates == 13 and model.replay_buffer.read_range("observations", 0, 100).dtype == np.uint8
    after = model.policy.actor.features_extractor.state_dict()
    assert any(not th.equal(value, initial[key]) for key, value in after.items())


@pytest.mark.parametrize("model_class", MODEL_LIST)
def test_cnn_policy_honours_normalize_images(model_class):
    """``normalize_images=False`` reaches every network: the CNN takes the pixels as they are (SB3's rule)."""
    env = FakeImageEnv(screen_height=36, screen_width=36, n_channels=1, discrete=False)
    kwargs = dict(net_arch=[16], features_extractor_kwargs=dict(features_dim=16))
    model = model_class("CnnPolicy", env, policy_kwargs=dict(normalize_images=False, **kwargs), buffer_size=10)
    networks = [model.policy.actor] + ([model.policy.critic] if model_class is not BC else [])
    assert not model.policy.normalize_images and all(not network.normalize_images for network in networks)
    obs = th.full((1, 1, 36, 36), 255, dtype=th.uint8)
    actor = model.policy.actor
    assert th.equal(actor.extract_features(obs, actor.features_extractor), actor.features_extractor(obs.float()))
    normalized = model_class("CnnPolicy", env, policy_kwargs=kwargs, buffer_size=10).policy.actor
    assert normalized.normalize_images
    assert th.equal(
        normalized.extract_features(obs, normalized.features_extractor), normalized.features_extractor(obs / 255.0)
    )


def test_crr_cnn_policy_per_source_actors_and_categorical_critic():
    """CRR's variants with ``CnnPolicy``: one CNN actor per source, a categorical critic on its own CNN's features."""
    image = spaces.Box(0, 255, (1, 36, 36), np.uint8)
    policy = CRRCnnPolicy(
        image,
        spaces.Box(-1, 1, (5,), np.float32),
        lambda _: 1e-3,
        n_actors=2,
        distributional_critic=True,
        n_atoms=11,
        net_arch=[16],
        features_extractor_kwargs=dict(features_dim=16),
    )
    cnns = [policy.actor.head(0).features_extractor, policy.actor.head(1).features_extractor, policy.critic.features_extractor]
    assert all(isinstance(cnn, NatureCNN) for cnn in cnns) and len({id(cnn) for cnn in cnns}) == 3
    obs = th.randint(0, 256, (4, 1, 36, 36), dtype=th.uint8)
    mean, std = policy.actor.distribution_params(obs, th.tensor([0, 1, 0, 1]))
    assert mean.shape == std.shape == (4, 5)
    first, second = policy.actor.head(0).distribution_params(obs), policy.actor.head(1).distribution_params(obs)
    th.testing.assert_close(mean[[0, 2]], first[0][[0, 2]])  # each row by its source's actor
    th.testing.assert_close(mean[[1, 3]], second[0][[1, 3]])
    assert policy.critic.q1_forward(obs, mean).shape == (4, 1)


@pytest.mark.parametrize("model_class", MODEL_LIST)
def test_cnn_policy_model_loads_with_safe_load(tmp_path, model_class):
    """A ``CnnPolicy`` model's zip loads with ``safe=True`` (its classes are the package's and SB3's), and only with its
    own algorithm's ``load``."""
    env = FakeImageEnv(screen_height=36, screen_width=36, n_channels=1, discrete=False)
    kwargs = dict(net_arch=[16], features_extractor_kwargs=dict(features_dim=16))
    model = model_class("CnnPolicy", env, buffer_size=10, policy_kwargs=kwargs, seed=0)
    model.save(tmp_path / "cnn.zip")
    loaded = model_class.load(tmp_path / "cnn.zip", safe=True)
    assert type(loaded.policy) is CNN_POLICIES[model_class]
    parameters_equal(model.get_parameters(), loaded.get_parameters())
    other = next(algorithm for algorithm in MODEL_LIST if algorithm is not model_class)
    with pytest.raises(ValueError, match=f"saved by {model_class.__name__}"):
        other.load(tmp_path / "cnn.zip")
