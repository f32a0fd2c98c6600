import os
import pathlib

import pytest
import torch as th

# One torch thread per test process: the suite runs with pytest-xdist on 2 cores.
th.set_num_threads(1)

_SHARED_MENAGERIE = pathlib.Path(__file__).resolve().parents[1].parent / "shared" / "menagerie"
if "MENAGERIE_ROOT" not in os.environ and _SHARED_MENAGERIE.is_dir():
    os.environ["MENAGERIE_ROOT"] = str(_SHARED_MENAGERIE)


@pytest.fixture(autouse=True)
def _single_torch_thread():
    th.set_num_threads(1)
    yield
