"""Command-line options generated from the config dataclasses (``n2f2.config.option``,
``add_config_options``, ``config_overrides``): on a small dataclass made here, whose expected help
texts and values are written out by hand, and spot checks of the real commands, whose preset
values are read from the presets themselves, not from the generated parser."""

from __future__ import annotations

import argparse
import dataclasses
from dataclasses import dataclass, replace
from typing import ClassVar, Optional

import pytest

from n2f2.cli import build_parser, main
from n2f2.config import ConfigDict, add_config_options, config_overrides, option, option_specs
from n2f2.validate import OPTION_TYPES, positive_float, positive_int


@dataclass
class Toy(ConfigDict):
    PRESETS: ClassVar[tuple[str, ...]] = ("small", "large")

    steps: int = option(10, help="number of steps", type=positive_int)
    rate: float = option(0.5, help="learning rate in 100% units", type=positive_float)
    mode: str = option("fast", help="how to run", choices=("fast", "exact"))
    cache: bool = option(True, help="keep a cache")
    cap: Optional[int] = option(None, help="upper bound", type=positive_int, flag="limit", metavar="N")
    hidden: int = 3  # not an option

    @staticmethod
    def small() -> "Toy":
        return Toy()

    @staticmethod
    def large() -> "Toy":
        return Toy(steps=1000, mode="exact", cap=7, cache=False)


def toy_parser(*args, **kwargs) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="toy")
    add_config_options(parser, Toy, *args, **kwargs)
    return parser


def helps(parser: argparse.ArgumentParser) -> dict[str, str]:
    """flag -> its help as --help prints it (``%%`` unescaped)."""
    return {flag: (action.help or "").replace("%%", "%") for action in parser._actions
            for flag in action.option_strings}


# ------------------------------------------------------------------------------------ the generator
def test_the_fields_declared_as_options_become_flags():
    flags = set(helps(toy_parser())) - {"-h", "--help"}
    assert flags == {"--steps", "--rate", "--mode", "--cache", "--no-cache", "--limit"}
    assert [f.name for f in dataclasses.fields(Toy)] == ["steps", "rate", "mode", "cache", "cap", "hidden"]
    assert Toy().steps == 10 and Toy().cap is None and Toy.steps == 10  # option() is a plain default


def test_help_is_the_field_text_and_every_presets_value():
    h = helps(toy_parser())
    assert h["--steps"] == "number of steps (small 10, large 1000)"
    assert h["--rate"] == "learning rate in 100% units (default 0.5)"  # both presets agree
    assert h["--mode"] == "how to run (small fast, large exact)"
    assert h["--cache"] == "keep a cache (small on, large off)"
    assert h["--limit"] == "upper bound (small none, large 7)"
    text = " ".join(toy_parser().format_help().split())  # "%" survives argparse's formatting
    assert "--limit N upper bound (small none, large 7)" in text
    assert "learning rate in 100% units (default 0.5)" in text


def test_help_reads_the_given_presets():
    h = helps(toy_parser(["steps"], presets={"a": Toy(steps=2), "b": Toy(steps=2)}))
    assert h["--steps"] == "number of steps (default 2)"
    assert set(h) == {"-h", "--help", "--steps"}


def test_unset_flags_keep_the_presets_values():
    args = toy_parser().parse_args([])
    assert config_overrides(args, Toy) == {}
    assert replace(Toy.large(), **config_overrides(args, Toy)) == Toy(steps=1000, mode="exact", cap=7, cache=False)


def test_given_flags_are_collected_under_the_field_names():
    args = toy_parser().parse_args(["--steps", "5", "--rate", "0.25", "--mode", "exact", "--no-cache", "--limit", "3"])
    assert config_overrides(args, Toy) == {"steps": 5, "rate": 0.25, "mode": "exact", "cache": False, "cap": 3}
    assert replace(Toy.small(), **config_overrides(args, Toy)) == Toy(steps=5, rate=0.25, mode="exact", cache=False,
                                                                      cap=3)
    assert config_overrides(toy_parser().parse_args(["--cache"]), Toy) == {"cache": True}


def test_a_command_can_rename_a_flag():
    parser = toy_parser({"steps": "toy-steps", "mode": "mode"})
    assert set(helps(parser)) == {"-h", "--help", "--toy-steps", "--mode"}
    args = parser.parse_args(["--toy-steps", "4"])
    assert args.toy_steps == 4
    assert config_overrides(args, Toy, {"steps": "toy-steps", "mode": "mode"}) == {"steps": 4}


@pytest.mark.parametrize("argv", [["--steps", "0"], ["--steps", "1.5"], ["--rate=-1"], ["--rate", "nan"],
                                  ["--mode", "slow"], ["--limit", "x"]])
def test_types_and_choices_refuse_bad_values(argv, capsys):
    with pytest.raises(SystemExit) as e:
        toy_parser().parse_args(argv)
    assert e.value.code == 2
    assert argv[0].split("=")[0] in capsys.readouterr().err


def test_an_unknown_field_is_an_error():
    with pytest.raises(ValueError, match="hidden"):
        toy_parser(["steps", "hidden"])


# ------------------------------------------------------------------------------------ the real commands
def command_help(capsys, command: str) -> str:
    with pytest.raises(SystemExit) as e:
        main([command, "--help"])
    assert e.value.code == 0
    return " ".join(capsys.readouterr().out.split())


def test_every_numeric_option_of_the_configs_has_a_validating_type():
    from n2f2.field.model import FieldConfig
    from n2f2.gaussians.fit import FitConfig
    from n2f2.segments.lifting import LiftSettings
    from n2f2.train.config import TrainConfig

    for cls in (FieldConfig, TrainConfig, FitConfig, LiftSettings):
        for name, (f, spec) in option_specs(cls).items():
            if spec.choices is None and not isinstance(f.default, (bool, str)):
                assert spec.type in OPTION_TYPES, f"{cls.__name__}.{name}"


def test_train_help_shows_each_presets_value(capsys):
    from n2f2.field.model import FieldConfig
    from n2f2.train.config import TrainConfig

    text = command_help(capsys, "train")
    cpu, paper = FieldConfig.cpu().plane_resolution, FieldConfig.paper().plane_resolution
    assert cpu != paper
    assert f"--plane-resolution PLANE_RESOLUTION TriPlane resolution: the side of each plane (cpu {cpu}, paper {paper})" \
        in text
    iters = f"(cpu {TrainConfig.cpu().iterations}, paper {TrainConfig.paper().iterations})"
    assert f"--iterations ITERATIONS optimisation steps of the field {iters}" in text
    assert "--blend-cache, --no-blend-cache" in text and "--deferred, --no-deferred" in text
    cpu_px, paper_px = TrainConfig.cpu().pixels_per_step, TrainConfig.paper().pixels_per_step
    assert f"(cpu {cpu_px}, paper {paper_px})" in text and (cpu_px, paper_px) == (2048, 4096)


def test_fit_and_run_help_show_each_presets_value(capsys):
    from n2f2.gaussians.fit import FitConfig
    from n2f2.pipeline.presets import get_preset

    text = command_help(capsys, "fit-gaussians")
    assert FitConfig.cpu().steps == 1500 and FitConfig.paper().steps == 30_000
    assert "as 3DGS (default 0)" in text and "here (cpu 1500, paper 30000)" in text
    assert f"(cpu {FitConfig.cpu().checkpoint_every}, paper {FitConfig.paper().checkpoint_every})" in text

    text = command_help(capsys, "run")
    cpu, paper = get_preset("cpu"), get_preset("paper")
    assert f"--train-steps TRAIN_STEPS optimisation steps of the field (cpu {cpu.train.iterations}, " \
           f"paper {paper.train.iterations})" in text
    assert f"(cpu {cpu.lift.scale_measure}, paper {paper.lift.scale_measure})" in text
    assert cpu.lift.scale_measure == "area" and paper.lift.scale_measure == "eigenvalue"


def test_train_flags_reach_the_configs():
    from n2f2.field.model import FieldConfig
    from n2f2.train.config import TrainConfig

    base = ["train", "DATA", "--gaussians", "G", "--segments", "S", "--out", "O"]
    args = build_parser().parse_args(base)
    assert config_overrides(args, FieldConfig) == {} and config_overrides(args, TrainConfig) == {}
    args = build_parser().parse_args(base + ["--plane-resolution", "64", "--variant", "flat", "--no-deferred",
                                             "--no-blend-cache", "--scale-jitter", "0.05"])
    assert config_overrides(args, FieldConfig) == {"plane_resolution": 64, "variant": "flat"}
    assert config_overrides(args, TrainConfig) == {"deferred": False, "blend_cache": False, "scale_jitter": 0.05}


def test_fit_segments_and_run_flags_reach_their_settings(tmp_path):
    from n2f2.gaussians.fit import FitConfig
    from n2f2.pipeline.commands import _run_options
    from n2f2.segments.commands import job_from_args

    def _lift_settings(args):
        return job_from_args(args).lift

    args = build_parser().parse_args(["fit-gaussians", "DATA", "--out", "O", "--depth-spread", "0.5", "--steps", "20"])
    assert config_overrides(args, FitConfig) == {"depth_spread_weight": 0.5, "steps": 20}

    seg = ["segments", "DATA", "--out", "B"]
    # The preset's measure, as `run` takes it: cpu (the default off CUDA) area, paper eigenvalue.
    assert _lift_settings(build_parser().parse_args(seg)).scale_measure == "area"
    assert _lift_settings(build_parser().parse_args(seg + ["--preset", "paper"])).scale_measure == "eigenvalue"
    assert _lift_settings(build_parser().parse_args(seg + ["--device", "cuda"])).scale_measure == "eigenvalue"
    assert _lift_settings(build_parser().parse_args(seg + ["--scale-measure", "extent"])).scale_measure == "extent"

    args = build_parser().parse_args(["run", "DATA", "--out", "O"])
    opts = _run_options(args, tmp_path, tmp_path / "run")
    assert (opts.fit_steps, opts.train_steps, opts.dim, opts.variant, opts.scale_measure) == (None,) * 5
    args = build_parser().parse_args(["run", "DATA", "--out", "O", "--fit-steps", "7", "--train-steps", "9",
                                      "--dim", "16", "--variant", "levels", "--scale-measure", "eigenvalue"])
    opts = _run_options(args, tmp_path, tmp_path / "run")
    assert (opts.fit_steps, opts.train_steps, opts.dim, opts.variant, opts.scale_measure) == \
        (7, 9, 16, "levels", "eigenvalue")
