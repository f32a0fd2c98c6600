"""
The files that let people adopt and cite the package: the licence setup.cfg names, the citation, the changelog; and
the package as a stranger gets it, a wheel and an sdist built from the checkout's files, the wheel used outside it.
"""

import configparser
import email
import json
import os
import pathlib
import re
import shutil
import subprocess
import sys
import tarfile
import zipfile

import pytest
import yaml

ROOT = pathlib.Path(__file__).resolve().parents[1]


def metadata() -> configparser.SectionProxy:
    config = configparser.ConfigParser()
    config.read(ROOT / "setup.cfg")
    return config["metadata"]


def test_license_is_the_one_setup_cfg_names():
    assert metadata()["license_expression"] == "MIT"
    text = (ROOT / "LICENSE").read_text()
    assert text.startswith("MIT License") and "Copyright (c)" in text and "sb3-lifelong developers" in text


def test_citation_names_the_package_and_the_paper():
    citation = yaml.safe_load((ROOT / "CITATION.cff").read_text())
    assert citation["cff-version"] == "1.2.0" and citation["type"] == "software"
    assert citation["license"] == metadata()["license_expression"]
    assert citation["version"] == (ROOT / "sb3_lifelong" / "version.txt").read_text().strip()
    paper = citation["preferred-citation"]
    assert paper["title"] == "Forgetting and Imbalance in Robot Lifelong Learning with Off-policy Data"
    assert paper["year"] == 2022 and len(paper["authors"]) == 8
    assert all(author["given-names"] and author["family-names"] for author in paper["authors"])


def test_changelog_records_the_change_of_mpos_default_torso():
    changelog = (ROOT / "CHANGELOG.md").read_text()
    version = (ROOT / "sb3_lifelong" / "version.txt").read_text().strip()
    assert f"- {version}" in changelog
    assert "MPO's default torso is LayerNorm" in changelog and "layer_norm=False" in changelog


# ---------------------------------------------------------------------------------------------- wheel and sdist
#: what a build reads besides the package (all in a fresh clone)
BUILD_FILES = "setup.py setup.cfg pyproject.toml MANIFEST.in README.md LICENSE CHANGELOG.md CITATION.cff".split()
#: the build, with the installed setuptools (no network): setuptools' PEP 517 hooks, as pip and python -m build call them
#: (they set sys.argv: the folder is read first)
BUILD = "import sys; from setuptools import build_meta as b; out = sys.argv[1]; b.build_sdist(out); b.build_wheel(out)"


def data_files() -> list[str]:
    """:return: the package's files that are not Python modules (what it reads at run time), as paths in a wheel"""
    found = []
    for path in sorted((ROOT / "sb3_lifelong").rglob("*")):
        if path.is_file() and path.suffix not in (".py", ".pyc") and "__pycache__" not in path.parts:
            found.append(path.relative_to(ROOT).as_posix())
    return found


@pytest.fixture(scope="module")
def built(tmp_path_factory) -> dict[str, pathlib.Path]:
    """The wheel and the sdist built from a copy of the checkout's files (a build in the checkout writes build/)."""
    root = tmp_path_factory.mktemp("package")
    source, out = root / "source", root / "dist"
    source.mkdir()
    for name in BUILD_FILES:
        shutil.copy2(ROOT / name, source / name)
    shutil.copytree(ROOT / "sb3_lifelong", source / "sb3_lifelong", ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    result = subprocess.run([sys.executable, "-c", BUILD, str(out)], cwd=source, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stdout + result.stderr
    assert "License classifiers are deprecated" not in result.stderr
    (wheel,) = out.glob("*.whl")
    (sdist,) = out.glob("*.tar.gz")
    return {"wheel": wheel, "sdist": sdist, "root": root}


def test_the_wheel_holds_every_file_the_package_reads(built):
    names = set(zipfile.ZipFile(built["wheel"]).namelist())
    expected = data_files()
    assert {"sb3_lifelong/version.txt", "sb3_lifelong/py.typed", "sb3_lifelong/zoo/hyperparams/mpo.yml"} <= set(expected)
    assert [name for name in expected if name not in names] == []
    modules = sorted(path.relative_to(ROOT).as_posix() for path in (ROOT / "sb3_lifelong").rglob("*.py"))
    assert [name for name in modules if name not in names] == []
    assert not [name for name in names if name.startswith(("tests/", "benchmarks/", "examples/", "docs/"))]


def test_the_metadata_states_author_licence_and_the_pythons_the_pins_allow(built):
    wheel = zipfile.ZipFile(built["wheel"])
    (info,) = [name for name in wheel.namelist() if name.endswith(".dist-info/METADATA")]
    meta = email.message_from_bytes(wheel.read(info))
    assert meta["Author"] == "sb3-lifelong developers" and meta["License-Expression"] == "MIT"
    assert meta["Requires-Python"] == ">=3.10"  # mujoco 3.17.0, gymnasium 1.4.0 and torch 2.13.0 need 3.10
    classifiers = meta.get_all("Classifier")
    versions = [c.rsplit(" ", 1)[-1] for c in classifiers if re.fullmatch(r"Programming Language :: Python :: 3\.\d+", c)]
    assert versions and all(tuple(map(int, v.split("."))) >= (3, 10) for v in versions)
    assert f"{sys.version_info.major}.{sys.version_info.minor}" in versions  # the Python the suite runs is claimed
    assert "Topic :: Scientific/Engineering :: Artificial Intelligence" in classifiers
    assert any(name.endswith(".dist-info/licenses/LICENSE") for name in wheel.namelist())


def test_the_sdist_holds_the_licence_citation_and_changelog_and_no_tests(built):
    with tarfile.open(built["sdist"]) as sdist:
        names = {name.split("/", 1)[1] for name in sdist.getnames() if "/" in name}
    assert {"LICENSE", "README.md", "CHANGELOG.md", "CITATION.cff", "sb3_lifelong/zoo/hyperparams/mpo.yml"} <= names
    assert not [name for name in names if name.startswith("tests/")]  # its tests need the repository: they stay there


#: run from the unpacked wheel, outside the checkout: where the package is, its files, a short training, the CLIs' help
OUTSIDE = """
import contextlib, io, json, sys
import sb3_lifelong, sb3_lifelong.zoo as zoo
from sb3_lifelong import MPO, LifelongReplayBuffer
found = {"package": sb3_lifelong.__file__, "version": sb3_lifelong.__version__}
found["hyperparams"] = [str(zoo.hyperparams_file(algo, preset)) for algo in zoo.ALGORITHMS
                        for preset in (None, *zoo.PRESETS[algo])]
model = MPO("MlpPolicy", "Pendulum-v1", learning_starts=20, batch_size=8, policy_kwargs={"net_arch": [8]},
            replay_buffer_class=LifelongReplayBuffer, replay_buffer_kwargs={"path": "buffer"})
model.learn(40)
found["learned"] = model.num_timesteps
import sb3_lifelong.buffers.__main__, sb3_lifelong.experiments.__main__, sb3_lifelong.zoo.__main__
found["help"] = {}
for name, module in [("experiments", sb3_lifelong.experiments.__main__), ("buffers", sb3_lifelong.buffers.__main__),
                     ("zoo", sb3_lifelong.zoo.__main__)]:
    text = io.StringIO()
    with contextlib.redirect_stdout(text), contextlib.suppress(SystemExit):
        module.main(["--help"])
    found["help"][name] = text.getvalue().splitlines()[0]
print(json.dumps(found))
"""


def test_the_wheel_runs_outside_the_checkout(built, tmp_path):
    """Unpacked (what installing a pure wheel does) and imported from a folder outside the repository."""
    site = tmp_path / "site"
    zipfile.ZipFile(built["wheel"]).extractall(site)
    env = {**os.environ, "PYTHONPATH": str(site), "OMP_NUM_THREADS": "1"}
    result = subprocess.run(
        [sys.executable, "-c", OUTSIDE], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600
    )
    assert result.returncode == 0, result.stderr
    found = json.loads(result.stdout.strip().splitlines()[-1])
    assert pathlib.Path(found["package"]).parent == site / "sb3_lifelong"  # the wheel's copy, not the checkout's
    assert found["version"] == (ROOT / "sb3_lifelong" / "version.txt").read_text().strip()
    files = [pathlib.Path(path) for path in found["hyperparams"]]
    assert files and all(path.is_file() and site in path.parents for path in files)
    assert found["learned"] == 40 and (tmp_path / "buffer" / "manifest.json").is_file()
    for name, usage in found["help"].items():
        assert usage.startswith(f"usage: python -m sb3_lifelong.{name} "), usage
