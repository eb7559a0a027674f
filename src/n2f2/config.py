"""The config dataclasses (``FitConfig``, ``FieldConfig``, ``TrainConfig``, ``LiftSettings``),
written once for every use:

* serialisation: they are saved as JSON in checkpoints and reports and read back with
  :meth:`ConfigDict.from_dict`, and the named presets (``cpu``, ``paper``) are their static
  constructors of the same name;
* command-line options: a field declared with :func:`option` carries its help text, argparse
  type and choices; :func:`add_config_options` turns such fields into flags whose help shows
  each preset's value, read from the presets, and :func:`config_overrides` collects the flags
  given. The commands hold no copy of a setting's text, type or default. Other settings
  dataclasses (``QueryConfig``, ``EvalConfig``, ``SfmSettings``, ``ViewerLimits``) declare their
  flags the same way; a command that reads a flag's value as it is gives it the field's own
  default (``field_defaults``), and :func:`field_default` reads one for a hand-written flag."""

from __future__ import annotations

import argparse
import dataclasses
from dataclasses import asdict, dataclass, fields
from typing import Any, Callable, ClassVar, Mapping, Optional, Sequence, TypeVar, Union

T = TypeVar("T", bound="ConfigDict")


# ----------------------------------------------------------------------------- presets
# The named presets of every stage: each config class has a static constructor of each name
# (FitConfig.cpu, TrainConfig.paper, ...), and n2f2.pipeline.presets gathers them per name.
PRESET_NAMES: tuple[str, ...] = ("cpu", "paper")
DEFAULT_PRESET = "cpu"


def default_preset(device: object = "cpu") -> str:
    """The preset a command uses when none is given: the paper's settings on a CUDA device,
    the small ``cpu`` ones elsewhere."""
    return "paper" if str(device).startswith("cuda") else DEFAULT_PRESET


def add_preset_option(parser: argparse.ArgumentParser, what: str) -> None:
    """``--preset`` with the same choices and default rule in every command; ``what`` says
    what each preset sets in this command."""
    parser.add_argument(
        "--preset",
        choices=PRESET_NAMES,
        default=None,
        help=f"{what} (default: {DEFAULT_PRESET}; paper with --device cuda)",
    )


@dataclass(kw_only=True)
class StageJob:
    """What the fit's, the bank's and the training's jobs take besides their inputs: the same
    flags in each command (:func:`stage_job_args`)."""

    downscale: float = 1.0  # image downscale factor, as 3DGS -r
    skip_missing: bool = False  # drop views whose image file is missing
    device: str = "cpu"
    resume: bool = False  # continue what OUT holds
    force: bool = False  # replace what OUT holds once the inputs are read
    progress: bool = True


def stage_job_args(args: argparse.Namespace) -> dict[str, Any]:
    """:class:`StageJob`'s fields from a command's parsed flags."""
    return dict(
        downscale=args.downscale,
        skip_missing=args.skip_missing,
        device=args.device,
        resume=args.resume,
        force=args.force,
        progress=not args.quiet,
    )


class ConfigDict:
    """Mixin for config dataclasses: ``to_dict``, ``from_dict`` and ``preset``."""

    PRESETS: ClassVar[tuple[str, ...]] = ()  # names of static constructors, e.g. PRESET_NAMES

    def to_dict(self) -> dict:
        return asdict(self)  # type: ignore[call-overload]

    @classmethod
    def from_dict(cls: type[T], d: dict) -> T:
        """Rebuild from :meth:`to_dict`'s output. Keys this version does not know are ignored (a
        checkpoint from another version still loads), and JSON lists become tuples again."""
        known = {f.name for f in fields(cls)}  # type: ignore[arg-type]
        kw: dict[str, Any] = {k: (tuple(v) if isinstance(v, list) else v) for k, v in d.items() if k in known}
        return cls(**kw)

    @classmethod
    def preset(cls: type[T], name: str) -> T:
        if name not in cls.PRESETS:
            raise ValueError(f"unknown preset {name!r}; choose from {sorted(cls.PRESETS)}")
        return getattr(cls, name)()


# ----------------------------------------------------------------------------- command-line options
OPTION_KEY = "n2f2.option"  # the dataclass field metadata key that option() fills
OPTION_FIELD = "n2f2_field"  # the argparse action attribute add_config_options sets: (class, field)


@dataclass(frozen=True)
class OptionSpec:
    """How a config field appears on the command line (stored in its field metadata)."""

    help: str  # what the setting does; the generated help adds each preset's value
    type: Optional[Callable[[str], Any]] = None  # argparse type (n2f2.validate's for numbers); None: str
    choices: Optional[tuple[Any, ...]] = None
    flag: Optional[str] = None  # the flag without "--" when not the field name in kebab case
    metavar: Optional[str] = None
    nargs: Optional[str] = None  # argparse nargs, e.g. "+" for a tuple field


def option(
    default: Any,
    *,
    help: str,
    type: Optional[Callable[[str], Any]] = None,
    choices: Optional[Sequence[Any]] = None,
    flag: Optional[str] = None,
    metavar: Optional[str] = None,
    nargs: Optional[str] = None,
) -> Any:
    """A dataclass field (``dataclasses.field(default=...)``) that is also a command-line option:
    :func:`add_config_options` makes ``--kebab-name`` of it with this help, type and choices.
    A bool field becomes ``--name / --no-name``."""
    spec = OptionSpec(help, type, None if choices is None else tuple(choices), flag, metavar, nargs)
    return dataclasses.field(default=default, metadata={OPTION_KEY: spec})


def option_specs(cls: type) -> dict[str, tuple[dataclasses.Field, OptionSpec]]:
    """``name -> (field, spec)`` of every field of dataclass ``cls`` declared with :func:`option`,
    in declaration order."""
    return {f.name: (f, f.metadata[OPTION_KEY]) for f in fields(cls) if OPTION_KEY in f.metadata}


def field_default(cls: type, name: str) -> Any:
    """The default of field ``name`` of dataclass ``cls`` (a ``default_factory`` called), for an
    option whose default cannot be None and must not be a second copy of it."""
    f = next((f for f in fields(cls) if f.name == name), None)
    if f is None:
        raise ValueError(f"{cls.__name__} has no field {name!r}")
    if f.default is not dataclasses.MISSING:
        return f.default
    if f.default_factory is not dataclasses.MISSING:
        return f.default_factory()
    raise ValueError(f"{cls.__name__}.{name} has no default")


def preset_configs(cls: type) -> dict[str, Any]:
    """``{preset name: instance}`` of ``cls``'s presets (``ConfigDict.PRESETS``), or
    ``{"default": cls()}`` for a dataclass without presets."""
    names = getattr(cls, "PRESETS", ())
    return {name: getattr(cls, name)() for name in names} if names else {"default": cls()}


def _shown(value: Any) -> str:
    if value is None:
        return "none"
    if isinstance(value, bool):
        return "on" if value else "off"
    if isinstance(value, float):
        return f"{value:g}"
    if isinstance(value, tuple):
        return " ".join(_shown(v) for v in value) or "none"
    return str(value)


def preset_values(presets: Mapping[str, Any], name: str) -> str:
    """``"cpu 128, paper 512"``: setting ``name`` under every preset, or ``"default 256"``
    when they all agree."""
    shown = {p: _shown(getattr(config, name)) for p, config in presets.items()}
    if len(set(shown.values())) == 1:
        return f"default {next(iter(shown.values()))}"
    return ", ".join(f"{p} {v}" for p, v in shown.items())


def option_flag(cls: type, name: str) -> str:
    """The flag of :func:`option` field ``name`` of ``cls``: ``--depth-spread``."""
    spec = option_specs(cls)[name][1]
    return "--" + (spec.flag or name.replace("_", "-"))


def _flags(cls: type, names: Union[None, Sequence[str], Mapping[str, str]]) -> dict[str, tuple[str, str]]:
    """``{field: (flag, dest)}`` of the chosen options: the field's own flag with the field name as
    dest, or a flag the command renames (``{"iterations": "train-steps"}``) with its own dest."""
    specs = option_specs(cls)
    if names is None:
        names = list(specs)
    renamed: Mapping[str, str] = names if isinstance(names, Mapping) else {}
    unknown = [n for n in names if n not in specs]
    if unknown:
        raise ValueError(f"{cls.__name__} declares no option {', '.join(unknown)} (see n2f2.config.option)")
    return {
        n: ("--" + renamed[n], renamed[n].replace("-", "_")) if n in renamed else (option_flag(cls, n), n)
        for n in names
    }


def add_config_options(
    parser: argparse.ArgumentParser,
    cls: type,
    names: Union[None, Sequence[str], Mapping[str, str]] = None,
    *,
    presets: Optional[Mapping[str, Any]] = None,
    field_defaults: bool = False,
) -> None:
    """Add a flag for each :func:`option` field of dataclass ``cls`` (``names``: only these, in
    this order; a mapping names their flags, ``{"iterations": "train-steps"}``). Each flag's
    default is None, meaning: keep the preset's value (see :func:`config_overrides`); with
    ``field_defaults``, the field's own default (for a command that reads the flag's value as
    it is). The help is the field's text followed by its value under each of ``presets``
    (``{name: config}``; default: ``cls``'s own presets), read from them. Each action records
    its field as ``(cls, name)`` in attribute :data:`OPTION_FIELD`."""
    presets = preset_configs(cls) if presets is None else presets
    specs = option_specs(cls)
    for name, (flag, dest) in _flags(cls, names).items():
        f, spec = specs[name]
        text = f"{spec.help} ({preset_values(presets, name)})".replace("%", "%%")
        default = field_default(cls, name) if field_defaults else None
        kw: dict[str, Any] = {"dest": dest, "default": default, "help": text}
        if isinstance(f.default, bool):
            kw["action"] = argparse.BooleanOptionalAction
        else:
            kw.update(choices=spec.choices, metavar=spec.metavar, nargs=spec.nargs)
            if spec.type is not None:
                kw["type"] = spec.type
        setattr(parser.add_argument(flag, **kw), OPTION_FIELD, (cls, name))


def config_overrides(
    args: argparse.Namespace, cls: type, names: Union[None, Sequence[str], Mapping[str, str]] = None
) -> dict[str, Any]:
    """``{field: value}`` of the options of ``cls`` that :func:`add_config_options` added with
    the same ``names`` and that were given on the command line, for
    ``dataclasses.replace(preset, **overrides)``; flags left out are not there."""
    given = {n: getattr(args, dest, None) for n, (_, dest) in _flags(cls, names).items()}
    return {n: v for n, v in given.items() if v is not None}
