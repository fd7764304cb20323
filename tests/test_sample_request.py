"""A sampling request is a typed config like training's and evaluation's: a YAML file, the flags users already type
(each a shorthand for one key), then dotted overrides, validated with errors naming the key."""

from __future__ import annotations

import argparse

import pytest
from conftest import load_launch_script

from mfm.composition import HUMANML3D_SWITCH
from pipeline.config import ConfigError
from pipeline.generation.request import (
    FLAGS,
    SampleRequest,
    SamplingError,
    add_request_flags,
    flag_values,
    load_sample_request,
)


def parse(argv: list[str]) -> dict:
    parser = argparse.ArgumentParser()
    add_request_flags(parser)
    return flag_values(parser.parse_args(argv))


def test_every_flag_names_a_request_key_with_a_doc():
    keys = {field for field in SampleRequest.__dataclass_fields__}
    assert {flag.key for flag in FLAGS} <= keys
    assert len({flag.name for flag in FLAGS}) == len(FLAGS)
    parser = argparse.ArgumentParser()
    add_request_flags(parser)
    undocumented = [a.option_strings[0] for a in parser._actions if a.option_strings and a.dest != "help"
                    and not a.help]
    assert not undocumented


def test_the_flags_users_type_set_the_same_request_as_keys():
    values = parse(["--checkpoint", "runs/x", "--out", "out/a", "--text", "a person walks: fast", "--text", "waves",
                    "--length", "40", "--length", "60", "--steps", "20", "--guidance", "3", "--no-video",
                    "--model-weights", "model", "--seed", "7"])
    from_flags = load_sample_request(None, (), values)
    from_keys = load_sample_request(None, ["checkpoint=runs/x", "out_dir=out/a", "texts=['a person walks: fast', waves]",
                                           "lengths=[40, 60]", "steps=20", "guidance=3", "video=false",
                                           "weights=model", "seed=7"])
    assert from_flags == from_keys
    assert from_flags.texts == ("a person walks: fast", "waves") and from_flags.lengths == (40, 60)
    assert from_flags.guidance == 3.0 and isinstance(from_flags.guidance, float) and from_flags.video is False


def test_yaml_then_flags_then_overrides(tmp_path):
    preset = tmp_path / "request.yaml"
    preset.write_text("checkpoint: runs/x\nout_dir: out/a\ntexts: [a person jumps]\nsteps: 50\nseed: 3\n")
    request = load_sample_request(preset, ["seed=9"], parse(["--steps", "25", "--seed", "4"]))
    assert (request.steps, request.seed, request.texts) == (25, 9, ("a person jumps",))


def test_edit_keep_options_and_composition_switch_from_the_command_line():
    values = parse(["--checkpoint", "c", "--out", "o", "--edit", "inbetween", "--source-motion", "walk.npy",
                    "--keep", "prefix=0.3", "--keep", "suffix=0.7"])
    request = load_sample_request(None, (), values)
    assert request.keep == {"prefix": "0.3", "suffix": "0.7"}
    switch = {"humanml3d": HUMANML3D_SWITCH, "3": 3, "0.25": 0.25, "1.0": 1.0}
    for text, expected in switch.items():
        request = load_sample_request(None, (), parse(["--checkpoint", "c", "--out", "o", "--text", "walks",
                                                       "--extrapolate", "--length", "40", "--switch", text]))
        assert request.switch == expected and type(request.switch) is type(expected), text
    # In YAML / overrides, 1.0 (a flow time: absolute-only) stays a float and 3 (steps) an int.
    request = load_sample_request(None, ["switch=1.0", "checkpoint=c", "out_dir=o", "texts=[w]", "extrapolate=true",
                                         "lengths=[40]"])
    assert request.switch == 1.0 and isinstance(request.switch, float)


def test_prompts_file_is_read_into_texts(tmp_path):
    prompts = tmp_path / "prompts.txt"
    prompts.write_text("# comment\na person walks\n\na person runs\n")
    request = load_sample_request(None, (), parse(["--checkpoint", "c", "--out", "o", "--text", "first",
                                                   "--prompts", str(prompts)]))
    assert request.texts == ("first", "a person walks", "a person runs") and request.prompts is None


def test_bad_keys_and_values_are_named():
    with pytest.raises(ConfigError, match="unknown config key 'stepz'"):
        load_sample_request(None, ["stepz=3", "checkpoint=c", "out_dir=o"])
    with pytest.raises(ConfigError, match="steps"):
        load_sample_request(None, ["steps=many", "checkpoint=c", "out_dir=o"])
    with pytest.raises(ConfigError, match="checkpoint"):
        load_sample_request(None, ["out_dir=o"])
    with pytest.raises((ConfigError, SamplingError), match="switch must be"):
        load_sample_request(None, ["switch=sometime", "checkpoint=c", "out_dir=o", "texts=[w]", "extrapolate=true",
                                   "lengths=[40]"])


def test_print_config_lists_every_key_with_its_meaning(capsys):
    sample = load_launch_script("sample").main
    assert sample(["--print-config", "--checkpoint", "c", "--out", "o", "--text", "walks", "steps=20"]) == 0
    printed = capsys.readouterr().out.splitlines()
    assert any(line.startswith("steps = 20  (default: null)  #") for line in printed)
    assert {line.split(" = ")[0] for line in printed} == set(SampleRequest.__dataclass_fields__)
    assert sample(["--checkpoint", "c", "--out", "o", "stepz=1"]) == 2
    assert "unknown config key 'stepz'" in capsys.readouterr().err
