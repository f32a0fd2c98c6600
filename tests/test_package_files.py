"""The files that let people adopt and cite the package: the licence setup.cfg names, the citation, the changelog."""

import configparser
import pathlib

import yaml

ROOT = pathlib.Path(__file__).resolve().parents[1]


def metadata() -> configparser.SectionProxy:
    config = configparser.ConfigParser()
    config.read(ROOT / "setup.cfg")
    return config["metadata"]


def test_license_is_the_one_setup_cfg_names():
    assert metadata()["license"] == "MIT"
    text = (ROOT / "LICENSE").read_text()
    assert text.startswith("MIT License") and "Copyright (c)" in text and "sb3-lifelong developers" in text


def test_citation_names_the_package_and_the_paper():
    citation = yaml.safe_load((ROOT / "CITATION.cff").read_text())
    assert citation["cff-version"] == "1.2.0" and citation["type"] == "software"
    assert citation["license"] == metadata()["license"]
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
