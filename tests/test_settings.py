"""Settings declared once: `SegmenterConfig` and `TrainConfig` fields carry their option, and
every command's options, the services' TOML keys and the flags one command gives another are
generated from them."""

from __future__ import annotations

import dataclasses

import pytest

from topseg.core.config import options_of, with_options
from topseg.core.crf import CRFConfig
from topseg.core.errors import ConfigError, TopsegError
from topseg.core.forest.train_config import TrainConfig
from topseg.core.segmenter_config import (
    BackgroundConfig,
    GridConfig,
    PostConfig,
    PreConfig,
    SegmenterConfig,
)
from topseg.services import cli
from topseg.services.batch.train import TrainJob
from topseg.services.cli.options import SEGMENTER_GROUPS, segmenter_config, setting_argv

#: commands that label frames and take every Segmenter setting
LABELLING = ("worker", "segment", "evaluate", "bench pipeline")
REQUIRED = {
    "worker": [],
    "segment": ["x.png", "--out", "o"],
    "evaluate": ["--data", "d"],
    "bench pipeline": [],
}


def parse(command: str, *argv: str):
    full = [*command.split(), *REQUIRED[command], *argv]
    return cli.build_parser(full).parse_args(full)


#: a configuration unlike the defaults in every setting that has an option
ODD = SegmenterConfig(
    pre=PreConfig(fill_holes_cm2=7.5),
    grid=GridConfig(downsample=1, stride=3, adaptive=0, early_exit=None, context_prior="off"),
    crf=CRFConfig(mode="exact", smoothness=2.5, noisy_smoothness=4.0),
    post=PostConfig(min_head_cm2=10.0, min_furniture_cm2=0.0, min_plant_cm2=20.0,
                    satellite_head_cm2=30.0, person_check="off", surface_vote="off"),
    background=BackgroundConfig(path="/etc/topseg/cell1-background.npz", sigmas=4.0,
                                margin_mm=12.5, mismatch_share=0.1),
)  # fmt: skip


def test_every_setting_has_a_unique_flag_in_its_group():
    paths = [p for p, _, _ in options_of(SegmenterConfig)]
    flags = [o.flag for _, _, o in options_of(SegmenterConfig)]
    assert len(set(flags)) == len(flags) == 19
    assert {p.split(".")[0] for p in paths} == set(SEGMENTER_GROUPS)
    for _, f, option in options_of(SegmenterConfig):
        assert option.help and f.name  # every option says what it does


def test_odd_differs_from_the_defaults_in_every_setting():
    default = SegmenterConfig()
    for path, _, _ in options_of(SegmenterConfig):
        group, name = path.split(".")
        assert getattr(getattr(ODD, group), name) != getattr(getattr(default, group), name), path


@pytest.mark.parametrize("command", LABELLING)
def test_each_labelling_command_takes_every_setting_and_reads_it_back(command):
    args = parse(command, *setting_argv(ODD))
    assert segmenter_config(args) == ODD
    assert segmenter_config(parse(command)) == SegmenterConfig()  # defaults from the fields


def test_the_worker_toml_takes_every_setting_by_its_flag(tmp_path):
    lines = ["[worker]"]
    argv = setting_argv(ODD)
    for flag, value in zip(argv[::2], argv[1::2], strict=True):
        number = value.replace(".", "", 1).isdigit()
        lines.append(f"{flag[2:]} = {value}" if number else f'{flag[2:]} = "{value}"')
    path = tmp_path / "worker.toml"
    path.write_text("\n".join(lines) + "\n")
    assert segmenter_config(parse("worker", "--config", str(path))) == ODD


def test_a_bad_value_is_refused_by_the_option_that_declares_it():
    with pytest.raises(TopsegError, match=r"--min-head-cm2 must be in \[0, 10000\]"):
        parse("worker", "--min-head-cm2", "-1")
    with pytest.raises(TopsegError, match=r"--downsample must be in \[1, 4\]"):
        parse("segment", "--downsample", "9")
    with pytest.raises(TopsegError, match="must be in"):
        parse("worker", "--early-exit", "1.5")


def test_a_nested_table_reads_the_same_configuration():
    table = {
        "pre": dataclasses.asdict(ODD.pre),
        "grid": dataclasses.asdict(ODD.grid),
        "crf": ODD.crf.to_dict(),
        "post": dataclasses.asdict(ODD.post),
        "background": dataclasses.asdict(ODD.background),
    }
    assert SegmenterConfig.from_dict(table) == ODD
    with pytest.raises(ConfigError, match="unknown key 'strid'"):
        SegmenterConfig.from_dict({"grid": {"strid": 2}})


def test_train_options_are_generated_from_train_config():
    flags = {o.flag for _, _, o in options_of(TrainConfig)}
    assert {"trees", "depth", "frames-per-tree", "features", "off-image", "edge-gaps"} <= flags
    argv = ["train", "--data", "d", "--out", "m.npz", "--trees", "3", "--features", "40",
            "--off-image", "background", "--split", "axis"]  # fmt: skip
    job = TrainJob.from_args(cli.build_parser(argv).parse_args(argv))
    want = TrainConfig(n_trees=3, split="axis")
    want = dataclasses.replace(
        want, features=dataclasses.replace(want.features, n_features=40, off_image="background")
    )
    assert job.config == want


def test_with_options_ignores_names_of_no_setting():
    config = with_options(TrainConfig(), {"trees": 2, "seed": 9, "data": {}})
    assert config == TrainConfig(n_trees=2)
