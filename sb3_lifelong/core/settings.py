"""
Groups of settings that mean one thing together, passed to an algorithm as one argument (a dataclass or a dict).

MPO's policy loss (:class:`sb3_lifelong.mpo.PolicyLossConfig`) and the compute settings that MPO and CRR share
(:class:`sb3_lifelong.numerics.ComputeSettings`) are such groups. Each is a frozen dataclass: its fields are checked
when it is made, it is saved with the model, and ``dataclasses.replace`` makes a changed copy.
"""

import dataclasses
from collections.abc import Mapping
from typing import Any, TypeVar

SelfSettings = TypeVar("SelfSettings", bound="Settings")


@dataclasses.dataclass(frozen=True)
class Settings:
    """Base of a group of settings: subclasses are frozen dataclasses that name their invalid fields."""

    def __post_init__(self) -> None:
        problems = self.invalid()
        if problems:
            values = ", ".join(f"{name}={getattr(self, name)!r}" for name in problems)
            rules = "; ".join(problems.values())
            raise ValueError(f"Invalid {type(self).__name__}: {values} ({rules})")

    def invalid(self) -> dict[str, str]:
        """:return: invalid field -> the rule it breaks (empty when every field is valid)"""
        return {}

    @classmethod
    def of(cls: type[SelfSettings], value: Any, argument: str) -> SelfSettings:
        """
        :param value: None (the defaults), an instance, or a mapping of some of the fields
        :param argument: the algorithm's argument that ``value`` was given as (named in errors)
        :return: the settings
        :raises TypeError: ``value`` is none of those, or a mapping names a field the settings do not have
        """
        if value is None:
            return cls()
        if isinstance(value, cls):
            return value
        if isinstance(value, Mapping):
            names = [field.name for field in dataclasses.fields(cls)]
            unknown = sorted(set(value) - set(names))
            if unknown:
                raise TypeError(f"{argument} has no setting {unknown}; its settings are {names}")
            return cls(**value)
        raise TypeError(f"{argument} must be a {cls.__name__}, a dict of its settings or None, got {value!r}")

    @classmethod
    def settled(cls: type[SelfSettings], attributes: dict[str, Any], argument: str) -> SelfSettings:
        """
        The settings that a model's attributes hold (at a setup, loads included): ``attributes[argument]`` read by
        :meth:`of` (a load may pass a dict), with the fields of a model saved before its settings were grouped, which
        it held as attributes of their own, moved into them (and out of ``attributes``).

        :param attributes: the model's attributes (its ``__dict__``)
        :param argument: the attribute (and argument) that holds the settings
        :return: the settings
        """
        settings = cls.of(attributes.get(argument), argument)
        flat = {field.name: attributes.pop(field.name) for field in dataclasses.fields(cls) if field.name in attributes}
        return dataclasses.replace(settings, **flat) if flat else settings
