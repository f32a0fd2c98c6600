"""The documentation builds in Sphinx's nitpicky mode with warnings as errors (``make doc``), offline."""

import importlib.util
import pathlib
import subprocess
import sys
import zlib

import pytest

DOCS = pathlib.Path(__file__).resolve().parents[1] / "docs"


def load_inventory_script():
    spec = importlib.util.spec_from_file_location("make_inventories", DOCS / "inventories" / "make_inventories.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def inventory_lines(data: bytes) -> list[str]:
    header_end = 0
    for _ in range(4):  # four header lines, then the zlib stream
        header_end = data.index(b"\n", header_end) + 1
    return zlib.decompress(data[header_end:]).decode().splitlines()


def test_inventories_are_up_to_date():
    """The committed ``docs/inventories/*.inv`` list what ``make_inventories.py`` says (run it after editing it)."""
    script = load_inventory_script()
    assert sorted(path.stem for path in (DOCS / "inventories").glob("*.inv")) == sorted(script.INVENTORIES)
    for name, (url, entries) in script.INVENTORIES.items():
        assert url.startswith("https://") and url.endswith("/"), url
        committed = inventory_lines((DOCS / "inventories" / f"{name}.inv").read_bytes())
        assert committed == inventory_lines(
            script.inventory_bytes(name, entries)
        ), f"docs/inventories/{name}.inv is out of date: python docs/inventories/make_inventories.py"


def test_docs_build_without_warnings(tmp_path):
    """Every cross-reference resolves (``-n``) and nothing warns (``-W``); no network (local inventories)."""
    pytest.importorskip("sphinx")
    pytest.importorskip("myst_parser")
    # the dummy builder reads every page and resolves every reference, as html does, without writing the pages
    command = [sys.executable, "-m", "sphinx", "-b", "dummy", "-n", "-W", "--keep-going", "-q", "-E"]
    result = subprocess.run(
        [*command, "-d", str(tmp_path / "doctrees"), str(DOCS), str(tmp_path / "out")],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert result.returncode == 0, f"the documentation does not build cleanly (make doc):\n{result.stderr[-5000:]}"
