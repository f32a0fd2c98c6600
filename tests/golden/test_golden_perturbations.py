"""
Golden values of the perturbation table (``sb3_lifelong.envs.perturbations.PERTURBATIONS``): the ranges, units and
observation scales users read in ``docs/modules/envs.md`` are the code's. First in the module's mutation set: most of
the table's mutants are module constants, which every test of the set would otherwise run for.
"""

import dataclasses
import pathlib
import re

import numpy as np
import pytest

from sb3_lifelong.envs import PERTURBATIONS

DOCS = pathlib.Path(__file__).resolve().parents[2] / "docs" / "modules" / "envs.md"


def test_the_docs_table_of_perturbations_is_the_codes() -> None:
    """``docs/modules/envs.md`` lists every perturbation with its unit, range and observation scale: each as in
    ``PERTURBATIONS`` (a range or scale changed in one place and not the other fails here)."""
    docs = DOCS.read_text()
    rows = re.findall(r"^\| `(\w+)` \| ([^|]+) \| [^|]+ \| \[([^,\]]+), ([^\]]+)\][^|]* \| ([^|]+) \|$", docs, re.M)
    number = {"pi": np.pi}
    table = {
        name: (unit.strip(), eval(low, {"__builtins__": {}}, number), eval(high, {"__builtins__": {}}, number), float(scale))
        for name, unit, low, high, scale in rows
    }
    assert list(table) == list(PERTURBATIONS)
    for name, p in PERTURBATIONS.items():
        assert table[name] == (p.unit, pytest.approx(p.low, rel=1e-12), pytest.approx(p.high, rel=1e-12), p.obs_scale), name
    with pytest.raises(dataclasses.FrozenInstanceError):
        PERTURBATIONS["friction"].low = -1.0  # type: ignore[misc]
