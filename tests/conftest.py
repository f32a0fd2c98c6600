import os
import pathlib

import pytest
import torch as th
from testkit import JOBS

from sb3_lifelong.experiments import PRESETS, run_seed

# One torch thread per test process: the suite runs with pytest-xdist on 2 cores.
th.set_num_threads(1)
# No cost log (sb3_lifelong.experiments.costs) from the tests' runs, and none read: a test that needs one sets its own
os.environ["SB3_LIFELONG_COSTS"] = ""

_SHARED_MENAGERIE = pathlib.Path(__file__).resolve().parents[1].parent / "shared" / "menagerie"
if "MENAGERIE_ROOT" not in os.environ and _SHARED_MENAGERIE.is_dir():
    os.environ["MENAGERIE_ROOT"] = str(_SHARED_MENAGERIE)


@pytest.fixture(autouse=True)
def _single_torch_thread():
    th.set_num_threads(1)
    yield


@pytest.fixture(scope="session")
def study(tmp_path_factory):
    """Two seeds of the tiny study with every job (shared, read-only, by the experiments and studies tests)."""
    output = tmp_path_factory.mktemp("study")
    messages: list[str] = []
    for seed in (0, 1):
        ran = run_seed(PRESETS["tiny"], seed, output, jobs=JOBS, log=messages.append)
        assert ran == JOBS
    return output, messages


@pytest.fixture(scope="session")
def small_collection(tmp_path_factory):
    """A study whose seed 0 has finished a small collection (``testkit.small_preset()``; shared: copy it to change it)."""
    from testkit import small_preset

    output = tmp_path_factory.mktemp("small_collection")
    assert run_seed(small_preset(), 0, output, jobs=["collect"], log=lambda m: None) == ["collect"]
    return output
