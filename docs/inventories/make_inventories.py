"""
Write the small intersphinx inventories that let the documentation link to Stable-Baselines3, Gymnasium, NumPy,
PyTorch and Python without a network connection.

Sphinx's intersphinx normally downloads each project's ``objects.inv``; CI and many build machines have no internet,
so ``docs/conf.py`` reads these local files instead (``intersphinx_mapping = {name: (url, local_file)}``): the links
in the built pages still point to the projects' real documentation at ``url``. Each file lists only the objects this
package's documentation refers to, with their page and anchor in that project's documentation, as the project's own
``objects.inv`` lists them (a name that a type hint spells by its defining module, e.g.
``gymnasium.core.Env``, links to the page that documents the public name, ``gymnasium.Env``).

When a docstring starts to refer to another outside object, ``make doc`` (``sphinx -n -W``) fails naming it: add it
below and run ``python docs/inventories/make_inventories.py`` (``tests/test_docs.py`` checks the files match).
"""

import os
import zlib

# project -> (documentation root, [(name, role, page#anchor)]); an anchor "$" is the name itself
INVENTORIES: dict[str, tuple[str, list[tuple[str, str, str]]]] = {
    "python": (
        "https://docs.python.org/3/",
        [
            ("collections.abc.Callable", "class", "library/collections.abc.html#$"),
            ("collections.abc.Iterable", "class", "library/collections.abc.html#$"),
            ("collections.abc.Iterator", "class", "library/collections.abc.html#$"),
            ("collections.abc.Mapping", "class", "library/collections.abc.html#$"),
            ("collections.abc.Sequence", "class", "library/collections.abc.html#$"),
            ("io.BufferedIOBase", "class", "library/io.html#$"),
            ("os.PathLike", "class", "library/os.html#$"),
            ("pathlib.Path", "class", "library/pathlib.html#$"),
            ("typing.Any", "data", "library/typing.html#$"),
            ("typing.Protocol", "class", "library/typing.html#$"),
            ("typing.NamedTuple", "class", "library/typing.html#$"),
            ("argparse.ArgumentParser", "class", "library/argparse.html#$"),
        ],
    ),
    "numpy": (
        "https://numpy.org/doc/stable/",
        [
            ("numpy.ndarray", "class", "reference/generated/numpy.ndarray.html#$"),
            ("numpy.dtype", "class", "reference/generated/numpy.dtype.html#$"),
            ("numpy.random.Generator", "class", "reference/random/generator.html#$"),
            ("numpy.random._generator.Generator", "class", "reference/random/generator.html#numpy.random.Generator"),
        ],
    ),
    "torch": (
        "https://docs.pytorch.org/docs/stable/",
        [
            ("torch.Tensor", "class", "tensors.html#$"),
            ("torch.device", "class", "tensor_attributes.html#$"),
            ("torch.dtype", "class", "tensor_attributes.html#$"),
            ("torch.nn.Module", "class", "generated/torch.nn.Module.html#$"),
            ("torch.nn.modules.module.Module", "class", "generated/torch.nn.Module.html#torch.nn.Module"),
            ("torch.nn.Linear", "class", "generated/torch.nn.Linear.html#$"),
            ("torch.nn.modules.linear.Linear", "class", "generated/torch.nn.Linear.html#torch.nn.Linear"),
            ("torch.optim.Optimizer", "class", "optim.html#$"),
        ],
    ),
    "pandas": (
        "https://pandas.pydata.org/docs/",
        [
            ("pandas.DataFrame", "class", "reference/api/pandas.DataFrame.html#$"),
            ("pandas.Series", "class", "reference/api/pandas.Series.html#$"),
        ],
    ),
    "gymnasium": (
        "https://gymnasium.farama.org/",
        [
            ("gymnasium.Env", "class", "api/env/#$"),
            ("gymnasium.core.Env", "class", "api/env/#gymnasium.Env"),
            ("gymnasium.Wrapper", "class", "api/wrappers/#$"),
            ("gymnasium.core.Wrapper", "class", "api/wrappers/#gymnasium.Wrapper"),
            ("gymnasium.Wrapper.env", "attribute", "api/wrappers/#$"),
            ("gymnasium.core.Wrapper.env", "attribute", "api/wrappers/#gymnasium.Wrapper.env"),
            ("gymnasium.spaces.Space", "class", "api/spaces/#$"),
            ("gymnasium.spaces.space.Space", "class", "api/spaces/#gymnasium.spaces.Space"),
            ("gymnasium.spaces.Box", "class", "api/spaces/fundamental/#$"),
            ("gymnasium.spaces.box.Box", "class", "api/spaces/fundamental/#gymnasium.spaces.Box"),
            ("gymnasium.spaces.Discrete", "class", "api/spaces/fundamental/#$"),
            ("gymnasium.spaces.Dict", "class", "api/spaces/composite/#$"),
            ("gymnasium.make", "function", "api/registry/#$"),
            ("gymnasium.envs.registration.EnvSpec", "class", "api/registry/#$"),
        ],
    ),
    "sb3": (
        "https://stable-baselines3.readthedocs.io/en/master/",
        [
            ("stable_baselines3.common.base_class.BaseAlgorithm", "class", "modules/base.html#$"),
            ("stable_baselines3.common.off_policy_algorithm.OffPolicyAlgorithm", "class", "modules/base.html#$"),
            ("stable_baselines3.common.callbacks.BaseCallback", "class", "guide/callbacks.html#$"),
            ("stable_baselines3.common.callbacks.EvalCallback", "class", "guide/callbacks.html#$"),
            ("stable_baselines3.common.vec_env.VecEnv", "class", "guide/vec_envs.html#$"),
            (
                "stable_baselines3.common.vec_env.base_vec_env.VecEnv",
                "class",
                "guide/vec_envs.html#stable_baselines3.common.vec_env.VecEnv",
            ),
            ("stable_baselines3.common.vec_env.VecNormalize", "class", "guide/vec_envs.html#$"),
            (
                "stable_baselines3.common.vec_env.vec_normalize.VecNormalize",
                "class",
                "guide/vec_envs.html#stable_baselines3.common.vec_env.VecNormalize",
            ),
            ("stable_baselines3.common.logger.Logger", "class", "common/logger.html#$"),
            ("stable_baselines3.common.noise.ActionNoise", "class", "common/noise.html#$"),
            ("stable_baselines3.common.evaluation.evaluate_policy", "function", "common/evaluation.html#$"),
            ("stable_baselines3.common.monitor.Monitor", "class", "common/monitor.html#$"),
            ("stable_baselines3.common.env_util.make_vec_env", "function", "common/env_util.html#$"),
        ],
    ),
}

HERE = os.path.dirname(os.path.abspath(__file__))


def inventory_bytes(project: str, entries: list[tuple[str, str, str]]) -> bytes:
    """:return: the ``objects.inv`` (Sphinx inventory version 2) listing ``entries`` of ``project``"""
    header = (
        f"# Sphinx inventory version 2\n# Project: {project}\n# Version: \n"
        "# The remainder of this file is compressed using zlib.\n"
    )
    lines = "".join(f"{name} py:{role} 1 {uri} -\n" for name, role, uri in sorted(entries))
    return header.encode() + zlib.compress(lines.encode(), 9)


def main() -> None:
    for name, (_, entries) in INVENTORIES.items():
        with open(os.path.join(HERE, f"{name}.inv"), "wb") as file:
            file.write(inventory_bytes(name, entries))


if __name__ == "__main__":
    main()
