"""Where a study's models run: the preset's ``device``, ``--device`` on the command line, and what is refused."""

import dataclasses
import json

import pytest
import torch as th

from sb3_lifelong.experiments.__main__ import main
from sb3_lifelong.experiments.jobs import model_kwargs
from sb3_lifelong.experiments.presets import PRESETS, Preset, check_device, same_settings
from sb3_lifelong.experiments.protocol import record_settings


def test_the_presets_run_on_the_cpu_and_every_model_gets_the_preset_device():
    assert all(preset.device == "cpu" for preset in PRESETS.values())
    assert model_kwargs(PRESETS["tiny"], 3)["device"] == "cpu"
    assert model_kwargs(dataclasses.replace(PRESETS["tiny"], device="cuda:1"), 3)["device"] == "cuda:1"


@pytest.mark.parametrize("name", ["gpu", "cuda:x", "meta", ""])
def test_a_name_that_is_no_study_device_is_refused(name):
    with pytest.raises(ValueError, match="device"):
        dataclasses.replace(PRESETS["tiny"], device=name)


def test_a_gpu_preset_can_be_described_on_a_machine_without_one():
    # the report of a study that ran on a GPU machine is read on a laptop: the name is checked, not the machine
    preset = dataclasses.replace(PRESETS["tiny"], device="cuda")
    assert preset.describe()["device"] == "cuda"
    assert Preset(**{**dataclasses.asdict(preset), "stages": preset.stages}).device == "cuda"


@pytest.mark.skipif(th.cuda.is_available(), reason="this machine has a CUDA GPU: the refusal needs one without")
def test_a_gpu_that_is_not_here_is_refused_before_anything_runs(tmp_path, capsys):
    with pytest.raises(ValueError, match="no CUDA GPU"):
        check_device("cuda")
    with pytest.raises(SystemExit):
        main(["run", "--preset", "tiny", "--seed", "0", "--output", str(tmp_path / "s"), "--device", "cuda"])
    assert "no CUDA GPU" in capsys.readouterr().err
    assert not (tmp_path / "s").exists()  # refused before the study's directory was made


def test_the_device_is_part_of_a_study_and_older_studies_read_as_cpu(tmp_path):
    cpu, gpu = PRESETS["tiny"], dataclasses.replace(PRESETS["tiny"], device="cuda")
    recorded = json.loads(json.dumps(cpu.describe()))
    del recorded["device"]  # a study recorded before there was a device setting ran on the CPU
    assert same_settings(recorded, json.loads(json.dumps(cpu.describe())))
    assert not same_settings(recorded, json.loads(json.dumps(gpu.describe())))
    record_settings(cpu, tmp_path)
    with pytest.raises(ValueError, match="device differ"):
        record_settings(gpu, tmp_path)
    assert json.loads((tmp_path / "preset.json").read_text())["device"] == "cpu"  # the recorded study is untouched


def test_run_on_a_study_of_another_device_exits_with_the_reason(tmp_path, capsys):
    output = tmp_path / "study"
    record_settings(dataclasses.replace(PRESETS["tiny"], device="cuda"), output)
    before = (output / "preset.json").read_bytes()
    with pytest.raises(SystemExit) as exited:
        main(["run", "--preset", "tiny", "--seed", "0", "--output", str(output), "--device", "cpu"])
    assert exited.value.code == 2 and "device differ" in capsys.readouterr().err
    assert (output / "preset.json").read_bytes() == before and sorted(p.name for p in output.iterdir()) == ["preset.json"]


def test_auto_records_the_device_it_chose(tmp_path):
    from sb3_lifelong.experiments.__main__ import _check_arguments, _parser

    parser = _parser()
    args = parser.parse_args(["run", "--preset", "tiny", "--seed", "0", "--output", str(tmp_path / "s"), "--device", "auto"])
    _check_arguments(parser, args)
    assert args.settings.device == ("cuda" if th.cuda.is_available() else "cpu")
