"""
Loading a saved model without running code from it (``MPO.load(path, safe=True)``, and the same for CRR and BC).

SB3's ``load`` unpickles the Python objects of a zip's ``data`` (spaces, schedules, classes, the last observations)
with cloudpickle: a tampered zip runs whatever its pickles ask for. Its state dicts are already read safely
(``torch.load(weights_only=True)``). With ``safe=True`` each pickled entry of ``data`` is read instead by
:class:`RestrictedUnpickler`, which resolves only the globals a model of this package saves and refuses anything else
(functions pickled by value, ``os.system``, ``builtins.exec``, ...) with ``pickle.UnpicklingError``; the objects are
then handed to SB3's ``load`` as ``custom_objects``, so that nothing else is unpickled.

What may be rebuilt: NumPy arrays, dtypes and random generators; Gymnasium spaces; ``collections.deque`` /
``OrderedDict``; ``pathlib`` paths; SB3's ``TrainFreq`` and schedule objects. What may only be referred to, never
called: policy classes and replay-buffer classes of SB3 and of this package, and torch module (activation) and
optimizer classes, e.g. in ``policy_kwargs``. A schedule saved as a Python function (``learning_rate=lambda p: ...``)
is code: refused; give it again with ``custom_objects={"learning_rate": ..., "lr_schedule": ...}``.

Whatever ``safe`` says, the plain-JSON ``replay_buffer_kwargs`` of a zip never make ``load`` write to a buffer
directory (create, evict, cut or delete its files): see :mod:`sb3_lifelong.common.reattach`.

What a zip says can also be read without unpickling anything: its ``data`` as JSON (:func:`saved_data`) and the
policy class it records (:func:`saved_policy_class`), with which ``load`` refuses a zip of another algorithm.
"""

import base64
import importlib
import io
import json
import pathlib
import pickle
import pickletools
import zipfile
from collections.abc import Mapping
from typing import Any, Optional, Union

#: globals that may be called while unpickling (data constructors that run no code of the file)
CONSTRUCTIBLE = frozenset(
    {
        ("builtins", "set"),
        ("builtins", "frozenset"),
        ("builtins", "complex"),
        ("builtins", "slice"),
        ("builtins", "bytearray"),
        ("collections", "deque"),
        ("collections", "OrderedDict"),
        ("pathlib", "Path"),
        ("pathlib", "PosixPath"),
        ("pathlib", "WindowsPath"),
        ("pathlib", "PurePosixPath"),
        ("pathlib", "PureWindowsPath"),
        ("numpy", "dtype"),
        ("numpy", "ndarray"),
        ("numpy.core.numeric", "_frombuffer"),
        ("numpy._core.numeric", "_frombuffer"),
        ("numpy.core.multiarray", "_reconstruct"),
        ("numpy._core.multiarray", "_reconstruct"),
        ("numpy.core.multiarray", "scalar"),
        ("numpy._core.multiarray", "scalar"),
        ("numpy.random._pickle", "__generator_ctor"),
        ("numpy.random._pickle", "__bit_generator_ctor"),
        ("numpy.random._pickle", "__randomstate_ctor"),
        ("numpy.random._generator", "Generator"),
        ("numpy.random.mtrand", "RandomState"),
        ("numpy.random._pcg64", "PCG64"),
        ("numpy.random._pcg64", "PCG64DXSM"),
        ("numpy.random._mt19937", "MT19937"),
        ("numpy.random._philox", "Philox"),
        ("numpy.random._sfc64", "SFC64"),
        ("numpy.random.bit_generator", "SeedSequence"),
        ("numpy.random.bit_generator", "__pyx_unpickle_SeedSequence"),
        ("stable_baselines3.common.type_aliases", "TrainFreq"),
        ("stable_baselines3.common.type_aliases", "TrainFrequencyUnit"),
        ("stable_baselines3.common.utils", "FloatSchedule"),
        ("stable_baselines3.common.utils", "ConstantSchedule"),
        ("stable_baselines3.common.utils", "LinearSchedule"),
    }
)
#: packages whose classes may be referred to (never called) when they are policies, buffers, torch modules or optimizers
REFERABLE_PACKAGES = ("sb3_lifelong.", "stable_baselines3.", "torch.nn.", "torch.optim.")
#: Gymnasium's space classes live in these modules
SPACE_MODULES = "gymnasium.spaces."


class ClassReference:
    """
    A class a pickle refers to but must not call (a policy or buffer class, a torch module or optimizer class):
    replaced by the class itself once the entry is unpickled (see :func:`resolve`).

    :param cls: The class
    """

    def __init__(self, cls: type) -> None:
        self.cls = cls

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        raise pickle.UnpicklingError(
            f"the pickle calls {self.cls.__module__}.{self.cls.__qualname__}: refused by safe=True (a class may only be "
            "referred to)"
        )


def _referable(obj: Any) -> bool:
    """Whether ``obj`` is a class that a saved model refers to without calling: policy, buffer, module, optimizer."""
    if not isinstance(obj, type):
        return False
    import torch as th
    from stable_baselines3.common.buffers import BaseBuffer
    from stable_baselines3.common.policies import BasePolicy

    return issubclass(obj, (BasePolicy, BaseBuffer, th.nn.Module, th.optim.Optimizer))


class RestrictedUnpickler(pickle.Unpickler):
    """
    An unpickler that resolves only the globals of :data:`CONSTRUCTIBLE`, Gymnasium's space classes, and (as
    :class:`ClassReference`, never callable) the policy, buffer, torch module and optimizer classes of SB3, this
    package and torch. Any other global raises ``pickle.UnpicklingError`` before its module is even imported.

    :param file: The pickle's bytes, as a binary file
    :param what: What is unpickled, for the messages
    """

    def __init__(self, file: io.BytesIO, what: str) -> None:
        super().__init__(file)
        self.what = what

    def find_class(self, module: str, name: str) -> Any:
        if (module, name) in CONSTRUCTIBLE:
            return super().find_class(module, name)
        if "." not in name and module.startswith(SPACE_MODULES):
            obj = getattr(importlib.import_module(module), name, None)
            from gymnasium.spaces import Space

            if isinstance(obj, type) and issubclass(obj, Space):
                return obj
        elif "." not in name and module.startswith(REFERABLE_PACKAGES):
            obj = getattr(importlib.import_module(module), name, None)
            if isinstance(obj, type) and _referable(obj):
                return ClassReference(obj)
        raise pickle.UnpicklingError(
            f"{self.what}: the pickle asks for {module}.{name}, which safe=True does not allow (it could run code). "
            "Load the file with safe=False only if you trust it, or give this entry with custom_objects"
        )


def resolve(obj: Any) -> Any:
    """``obj`` with every :class:`ClassReference` in it (in dicts, lists and tuples) replaced by its class."""
    if isinstance(obj, ClassReference):
        return obj.cls
    if isinstance(obj, dict):
        resolved = {key: resolve(value) for key, value in obj.items()}
        return resolved if type(obj) is dict else type(obj)(resolved)  # e.g. an OrderedDict
    if isinstance(obj, list):
        return [resolve(value) for value in obj]
    if isinstance(obj, tuple) and type(obj) is tuple:
        return tuple(resolve(value) for value in obj)
    return obj


def restricted_loads(data: bytes, what: str) -> Any:
    """
    :param data: A pickle
    :param what: What it is, for the messages
    :return: The object, unpickled by :class:`RestrictedUnpickler`
    :raises pickle.UnpicklingError: naming ``what`` and the refused global
    """
    return resolve(RestrictedUnpickler(io.BytesIO(data), what).load())


def safe_custom_objects(saved: Mapping[str, Any], custom_objects: Mapping[str, Any], where: str) -> dict[str, Any]:
    """
    Unpickle every pickled entry of a saved model's ``data`` with :func:`restricted_loads`, for SB3's ``load``.

    :param saved: The zip's ``data``, parsed as JSON (nothing unpickled)
    :param custom_objects: Entries given by the caller (not unpickled, kept as given)
    :param where: The saved model, for the messages
    :return: ``custom_objects`` plus every other pickled entry of ``data``, unpickled
    :raises pickle.UnpicklingError: an entry asks for a global that is not allowed
    """
    objects = dict(custom_objects)
    for key, value in saved.items():
        if key in objects or not (isinstance(value, dict) and ":serialized:" in value):
            continue
        raw = base64.b64decode(value[":serialized:"].encode())
        objects[key] = restricted_loads(raw, f"{where}: data[{key!r}]")
    return objects


def saved_data(path: Union[str, pathlib.Path, io.BufferedIOBase]) -> Optional[dict[str, Any]]:
    """
    The ``data`` of a saved model, parsed as JSON: its pickled entries stay base64 text, nothing is unpickled.

    :param path: The zip (``.zip`` added if missing, as SB3 does) or a seekable file object (read, then put back)
    :return: The document, or None when it cannot be read (not a zip, no ``data``: SB3's load reports it)
    """
    try:
        if isinstance(path, (str, pathlib.Path)):
            name = pathlib.Path(path)
            if not name.exists():  # SB3 adds the suffix to a path that does not exist
                name = name.with_name(name.name + ".zip")
            with zipfile.ZipFile(name) as archive:
                data = json.loads(archive.read("data"))
        elif path.seekable():
            position = path.tell()
            try:
                with zipfile.ZipFile(path) as archive:
                    data = json.loads(archive.read("data"))
            finally:
                path.seek(position)
        else:
            return None
    except Exception:
        return None
    return data if isinstance(data, dict) else None


def saved_policy_class(data: dict[str, Any]) -> Optional[tuple[str, str]]:
    """
    The policy class recorded in a saved model's ``data``, read without unpickling anything: the module and name that
    the pickled class reference of ``data["policy_class"]`` pushes (the pickle's opcodes are only listed, never run).

    :param data: The ``data`` of the zip (see :func:`saved_data`)
    :return: ``(module, name)``, or None when it cannot be told
    """
    try:
        serialized = base64.b64decode(data["policy_class"][":serialized:"].encode())
        strings: list[str] = []
        for opcode, argument, _ in pickletools.genops(serialized):
            if isinstance(argument, str) and opcode.name in ("SHORT_BINUNICODE", "BINUNICODE", "UNICODE", "BINUNICODE8"):
                strings.append(argument)
            elif opcode.name == "STACK_GLOBAL" and len(strings) >= 2:
                return strings[-2], strings[-1]
            elif opcode.name == "GLOBAL" and isinstance(argument, str) and " " in argument:
                module, qualname = argument.split(" ", 1)
                return module, qualname
    except Exception:  # not the expected pickle: SB3's load reports it
        return None
    return None
