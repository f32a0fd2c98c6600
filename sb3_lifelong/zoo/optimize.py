"""
Hyperparameter search spaces of MPO and CRR for rl-zoo3's ``-optimize`` (Optuna).

:func:`sb3_lifelong.zoo.register` adds them to ``rl_zoo3.hyperparams_opt.HYPERPARAMS_SAMPLER`` and
``HYPERPARAMS_CONVERTER`` under the zoo's names ``mpo`` and ``crr``, so that::

    python -m sb3_lifelong.zoo train --algo mpo --env Hopper-v5 -optimize --n-trials 50 --n-evaluations 4

searches them as the zoo searches SAC's. As in the zoo, a sampler draws the raw parameters of a trial (what
``trial.params`` records: ``one_minus_gamma``, ``batch_size_pow``, ``net_arch`` by name, ...) and a converter turns
them into the algorithm's keyword arguments; ``--trial-id`` reloads a trial through the converter.
"""

from typing import Any

__all__ = [
    "CONVERTERS",
    "NET_ARCHS",
    "SAMPLERS",
    "convert_crr_params",
    "convert_mpo_params",
    "sample_crr_params",
    "sample_mpo_params",
]

#: the network sizes a trial chooses between, by name (the same names and sizes as the zoo's off-policy samplers)
NET_ARCHS: dict[str, list[int]] = {"small": [64, 64], "medium": [256, 256], "big": [400, 300]}


def _common(params: dict[str, Any]) -> dict[str, Any]:
    """The parameters both algorithms share: discount, batch size and network, as keyword arguments."""
    net_arch = params["net_arch"]
    if net_arch not in NET_ARCHS:
        raise ValueError(f"unknown net_arch {net_arch!r} in the trial's parameters; known: {sorted(NET_ARCHS)}")
    return {
        "gamma": 1.0 - float(params["one_minus_gamma"]),
        "learning_rate": float(params["learning_rate"]),
        "batch_size": 2 ** int(params["batch_size_pow"]),
        "policy_kwargs": {"net_arch": list(NET_ARCHS[net_arch]), "layer_norm": bool(params["layer_norm"])},
    }


def _sample_common(trial: Any) -> dict[str, Any]:
    params = {
        "one_minus_gamma": trial.suggest_float("one_minus_gamma", 0.0001, 0.03, log=True),
        "learning_rate": trial.suggest_float("learning_rate", 1e-5, 2e-3, log=True),
        "batch_size_pow": trial.suggest_int("batch_size_pow", 6, 9),  # 64 to 512
        "net_arch": trial.suggest_categorical("net_arch", list(NET_ARCHS)),
        "layer_norm": trial.suggest_categorical("layer_norm", [True, False]),
    }
    trial.set_user_attr("gamma", 1.0 - params["one_minus_gamma"])
    trial.set_user_attr("batch_size", 2 ** params["batch_size_pow"])
    return params


def convert_mpo_params(params: dict[str, Any]) -> dict[str, Any]:
    """
    :param params: a trial's raw parameters (see :func:`sample_mpo_params`)
    :return: MPO's keyword arguments
    """
    return {
        **_common(params),
        "num_samples": int(params["num_samples"]),
        "policy_loss": {"epsilon": float(params["epsilon"]), "epsilon_mean": float(params["epsilon_mean"])},
        "target_update_interval": int(params["target_update_interval"]),
    }


def sample_mpo_params(trial: Any, n_actions: int, n_envs: int, additional_args: dict) -> dict[str, Any]:
    """
    Draw MPO's hyperparameters for one Optuna trial: the discount, learning rate, batch size, network (size and
    LayerNorm torso), the number of sampled actions, the E-step's KL bound ``epsilon``, the M-step's mean bound
    ``epsilon_mean`` and the period of the hard target copies.

    :param trial: the Optuna trial
    :param n_actions: the action dimension (unused: MPO needs no action noise)
    :param n_envs: the number of environments (unused)
    :param additional_args: the zoo's extra arguments (unused)
    :return: MPO's keyword arguments
    """
    params = _sample_common(trial)
    params["num_samples"] = trial.suggest_categorical("num_samples", [10, 20, 40])
    params["epsilon"] = trial.suggest_float("epsilon", 0.01, 0.5, log=True)
    params["epsilon_mean"] = trial.suggest_float("epsilon_mean", 1e-4, 1e-2, log=True)
    params["target_update_interval"] = trial.suggest_categorical("target_update_interval", [50, 100, 250])
    return convert_mpo_params(params)


def convert_crr_params(params: dict[str, Any]) -> dict[str, Any]:
    """
    :param params: a trial's raw parameters (see :func:`sample_crr_params`)
    :return: CRR's keyword arguments
    """
    return {
        **_common(params),
        "advantage_transform": str(params["advantage_transform"]),
        "beta": float(params["beta"]),
        "num_samples": int(params["num_samples"]),
    }


def sample_crr_params(trial: Any, n_actions: int, n_envs: int, additional_args: dict) -> dict[str, Any]:
    """
    Draw CRR's hyperparameters for one Optuna trial: the discount, learning rate, batch size, network (size and
    LayerNorm torso), the advantage transform (``exp`` or ``indicator``), its temperature ``beta`` and the number of
    actions sampled for the advantage baseline.

    :param trial: the Optuna trial
    :param n_actions: the action dimension (unused)
    :param n_envs: the number of environments (unused)
    :param additional_args: the zoo's extra arguments (unused)
    :return: CRR's keyword arguments
    """
    params = _sample_common(trial)
    params["advantage_transform"] = trial.suggest_categorical("advantage_transform", ["exp", "indicator"])
    params["beta"] = trial.suggest_float("beta", 0.1, 10.0, log=True)
    params["num_samples"] = trial.suggest_categorical("num_samples", [4, 10, 20])
    return convert_crr_params(params)


#: the zoo's samplers and converters of this package's algorithms, by the zoo's algorithm names
SAMPLERS = {"mpo": sample_mpo_params, "crr": sample_crr_params}
CONVERTERS = {"mpo": convert_mpo_params, "crr": convert_crr_params}
