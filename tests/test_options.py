"""Every command-line option's default against the dataclass field it stands for, so that a
default is written once (in the dataclass) and ``--help`` shows that value:

* on the real parser (``n2f2.cli.build_parser``): an option :func:`n2f2.config.add_config_options`
  made (it records its field) defaults to the field's default, or to None ("keep the preset's
  value"); so does every other option of the command whose dest is a field of one of those
  classes (``--seed``, ``--rescale-labels``, ...);
* in the source, parsed with ``ast``: no ``add_argument(..., default=LITERAL)`` whose literal
  equals the default of a field named as the option's dest in a settings class (a dataclass
  of the package with :func:`~n2f2.config.option` fields: the classes commands make options
  of). Defaults read from the dataclass or from a named constant are not literals and pass;
  None is the "keep the config's value" marker and passes.

Each checker is also run on a small case made here that it must reject."""

from __future__ import annotations

import argparse
import ast
import dataclasses
import importlib
import inspect
from pathlib import Path
from typing import Any, Iterator

import pytest

import n2f2
from n2f2.cli import build_parser
from n2f2.config import OPTION_FIELD, add_config_options, field_default, option, option_specs

PACKAGE_ROOT = Path(n2f2.__file__).parent

# --device is one option of every command (validate.add_device_option), "cpu" unless given, as
# every config, job and function of the package defaults to; no single dataclass owns it.
NOT_A_COPY = {"device"}


def subcommands(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    """``{command: its parser}`` of every subcommand."""
    found = {}
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            found.update(action.choices)
    return found


def _same(a: Any, b: Any) -> bool:
    """Equal values, lists and tuples alike; a bool never equals a number."""
    a, b = (tuple(v) if isinstance(v, list) else v for v in (a, b))
    return isinstance(a, bool) == isinstance(b, bool) and a == b


def _fields(cls: type) -> dict[str, Any]:
    return {f.name: field_default(cls, f.name) for f in dataclasses.fields(cls)
            if f.default is not dataclasses.MISSING or f.default_factory is not dataclasses.MISSING}


def default_mismatches(parser: argparse.ArgumentParser) -> list[str]:
    """``"command --flag: default X, Cls.field Y"`` for each option of each subcommand whose
    default is neither None nor its field's default. An option's field is the one
    add_config_options recorded on it, else a same-named field of a class whose options the
    command has."""
    problems = []
    for command, sub in subcommands(parser).items():
        classes = {getattr(a, OPTION_FIELD)[0] for a in sub._actions if hasattr(a, OPTION_FIELD)}
        for action in sub._actions:
            tie = getattr(action, OPTION_FIELD, None)
            ties = [tie] if tie else [(cls, action.dest) for cls in classes if action.dest in _fields(cls)]
            for cls, name in ties:
                expected = field_default(cls, name)
                if action.default is not None and not _same(action.default, expected):
                    flag = "/".join(action.option_strings)
                    problems.append(f"{command} {flag}: default {action.default!r}, "
                                    f"{cls.__name__}.{name} {expected!r}")
    return problems


def generated_fields(parser: argparse.ArgumentParser) -> set[tuple[str, str, str]]:
    """``(command, class name, field)`` of every option add_config_options made."""
    return {(command, getattr(a, OPTION_FIELD)[0].__name__, getattr(a, OPTION_FIELD)[1])
            for command, sub in subcommands(parser).items() for a in sub._actions if hasattr(a, OPTION_FIELD)}


# ------------------------------------------------------------------------------------ the real parser
def test_every_option_of_a_dataclass_field_defaults_to_it():
    assert default_mismatches(build_parser()) == []


def test_the_settings_classes_make_their_commands_options():
    got = generated_fields(build_parser())
    expected = {
        ("query", "QueryConfig", "composite_weights"), ("query", "QueryConfig", "temperature"),
        ("query", "QueryConfig", "render"), ("query", "QueryConfig", "canonical"),
        ("query", "QueryConfig", "selection"),
        ("eval", "QueryConfig", "composite_weights"), ("eval", "QueryConfig", "temperature"),
        ("eval", "QueryConfig", "render"), ("eval", "EvalConfig", "modes"),
        ("sfm", "SfmSettings", "matcher"), ("sfm", "SfmSettings", "camera_model"),
        ("sfm", "SfmSettings", "max_image_size"),
        ("view", "ViewerLimits", "max_queries"), ("view", "ViewerLimits", "max_body_bytes"),
        ("fit-gaussians", "FitConfig", "steps"), ("train", "TrainConfig", "iterations"),
        ("train", "FieldConfig", "dim"), ("segments", "LiftSettings", "scale_measure"),
        ("run", "TrainConfig", "iterations"),
    }
    assert expected <= got, sorted(expected - got)


def test_options_read_as_they_are_default_to_the_field():
    """The flags whose commands read them without config_overrides have the field's own value."""
    from n2f2.data.sfm import SfmSettings
    from n2f2.query.engine import QueryConfig

    parser = build_parser()
    query = parser.parse_args(["query", "RUN", "text", "--out", "O"])
    assert (query.selection, query.render, query.composite_weights) == \
        (QueryConfig().selection, QueryConfig().render, QueryConfig().composite_weights)
    assert query.temperature is None and query.canonical is None  # None: QueryConfig's
    sfm = parser.parse_args(["sfm", "PHOTOS", "--out", "D"])
    d = SfmSettings()
    assert (sfm.matcher, sfm.camera_model, sfm.max_image_size, sfm.per_image_camera) == \
        (d.matcher, d.camera_model, d.max_image_size, d.per_image_camera)


def test_the_viewers_defaults_are_its_settings():
    from n2f2.config import config_overrides
    from n2f2.viewer import commands
    from n2f2.viewer.server import api_server
    from n2f2.viewer.settings import API_PORT, HOST, VIEWER_PORT, ViewerLimits

    args = build_parser().parse_args(["view", "RUN"])
    assert (args.port, args.api_port, args.host) == (VIEWER_PORT, API_PORT, HOST)
    assert args.cache_mb * 2**20 == ViewerLimits().render_cache_bytes
    assert ViewerLimits(**config_overrides(args, ViewerLimits, commands.LIMIT_FLAGS)) == ViewerLimits()
    launch = inspect.signature(commands.launch).parameters
    assert (launch["port"].default, launch["api_port"].default, launch["host"].default) == (VIEWER_PORT, API_PORT, HOST)
    served = inspect.signature(api_server).parameters
    assert (served["port"].default, served["host"].default) == (API_PORT, HOST)


def test_each_port_is_written_once():
    """7007 and 7008 appear as numbers in one place of the package: viewer/settings.py."""
    from n2f2.viewer.settings import API_PORT, VIEWER_PORT

    where: dict[int, list[str]] = {VIEWER_PORT: [], API_PORT: []}
    for path in PACKAGE_ROOT.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
            if isinstance(node, ast.Constant) and type(node.value) is int and node.value in where:
                where[node.value].append(f"{path.relative_to(PACKAGE_ROOT)}:{node.lineno}")
    assert {port: len(places) for port, places in where.items()} == {VIEWER_PORT: 1, API_PORT: 1}, where


# ------------------------------------------------------------------------------------ the source
def _module_name(path: Path) -> str:
    parts = list(path.relative_to(PACKAGE_ROOT.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _is_dataclass_decorator(node: ast.expr) -> bool:
    target = node.func if isinstance(node, ast.Call) else node
    return (isinstance(target, ast.Name) and target.id == "dataclass") or \
        (isinstance(target, ast.Attribute) and target.attr == "dataclass")


def package_dataclasses(root: Path = PACKAGE_ROOT) -> Iterator[type]:
    """Every dataclass defined at the top level of a module of the package."""
    for path in sorted(root.rglob("*.py")):
        tree = ast.parse(path.read_text(), filename=str(path))
        names = [node.name for node in tree.body
                 if isinstance(node, ast.ClassDef) and any(map(_is_dataclass_decorator, node.decorator_list))]
        if names:
            module = importlib.import_module(_module_name(path))
            yield from (getattr(module, name) for name in names)


def field_defaults_by_name(classes) -> dict[str, list[tuple[str, Any]]]:
    """``{field name: [(Class.field, default), ...]}`` over ``classes``."""
    by_name: dict[str, list[tuple[str, Any]]] = {}
    for cls in classes:
        for name, default in _fields(cls).items():
            by_name.setdefault(name, []).append((f"{cls.__name__}.{name}", default))
    return by_name


def _dest(call: ast.Call) -> str | None:
    for kw in call.keywords:
        if kw.arg == "dest" and isinstance(kw.value, ast.Constant):
            return kw.value.value
    flags = [a.value for a in call.args if isinstance(a, ast.Constant) and isinstance(a.value, str)]
    longs = [f for f in flags if f.startswith("--")]
    flag = (longs or flags or [None])[0]
    return None if flag is None else flag.lstrip("-").replace("-", "_")


def copied_defaults(root: Path, fields_by_name: dict[str, list[tuple[str, Any]]]) -> list[str]:
    """``"file:line dest NAME: default X copies Class.field"`` for each ``add_argument`` call in the
    package at ``root`` whose ``default=`` is a literal other than None equal to the default of
    a dataclass field named as the option's dest."""
    problems = []
    for path in sorted(root.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
            if not (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
                    and node.func.attr == "add_argument"):
                continue
            default = next((kw.value for kw in node.keywords if kw.arg == "default"), None)
            dest = _dest(node)
            if default is None or dest is None or dest in NOT_A_COPY:
                continue
            try:
                value = ast.literal_eval(default)
            except ValueError:  # a name, attribute or call: read from where the value is written
                continue
            if value is None:
                continue
            for where, field_value in fields_by_name.get(dest, []):
                if _same(value, field_value):
                    problems.append(f"{path.relative_to(root)}:{node.lineno} dest {dest}: default {value!r} "
                                    f"copies {where}")
    return problems


def test_no_add_argument_copies_a_dataclass_default():
    classes = [cls for cls in package_dataclasses() if option_specs(cls)]
    names = {cls.__name__ for cls in classes}
    assert names >= {"QueryConfig", "SfmSettings", "ViewerLimits", "EvalConfig", "FitConfig", "TrainConfig",
                     "FieldConfig", "LiftSettings"}
    assert copied_defaults(PACKAGE_ROOT, field_defaults_by_name(classes)) == []


# ------------------------------------------------------------------------------------ the checkers
@dataclasses.dataclass
class Settings:
    size: int = option(4, help="a size")
    mode: str = "fast"
    scales: tuple[int, ...] = (1, 2)


def test_the_source_checker_finds_a_copied_default(tmp_path):
    (tmp_path / "commands.py").write_text(
        "def register(p):\n"
        "    p.add_argument('--size', type=int, default=4)\n"  # a copy of Settings.size
        "    p.add_argument('--other-mode', dest='mode', default='fast')\n"  # a copy, under another flag
        "    p.add_argument('--scales', nargs='+', default=[1, 2])\n"  # a copy, as a list
        "    p.add_argument('--mode-b', default='fast')\n"  # no field mode_b: not a copy
        "    p.add_argument('--size-b', default=None)\n"  # None: keep the config's value
        "    p.add_argument('--device', default='cpu')\n"  # shared by every command
        "    p.add_argument('--size', default=SIZE)\n"  # read from a name, not written here
        "    p.add_argument('--size', default=5)\n"  # another value
    )
    problems = copied_defaults(tmp_path, field_defaults_by_name([Settings]))
    assert problems == ["commands.py:2 dest size: default 4 copies Settings.size",
                        "commands.py:3 dest mode: default 'fast' copies Settings.mode",
                        "commands.py:4 dest scales: default [1, 2] copies Settings.scales"]


def test_the_parser_checker_finds_a_default_that_differs():
    parser = argparse.ArgumentParser(prog="n2f2")
    sub = parser.add_subparsers().add_parser("toy")
    add_config_options(sub, Settings)  # --size, default None: fine
    sub.add_argument("--mode", default="exact")  # named as a field of Settings, another value
    sub.add_argument("--scales", nargs="+", type=int, default=[1, 2])  # the field's value, as a list
    assert default_mismatches(parser) == ["toy --mode: default 'exact', Settings.mode 'fast'"]
    other = argparse.ArgumentParser(prog="n2f2")
    action = other.add_subparsers().add_parser("toy").add_argument("--size", default=5)
    setattr(action, OPTION_FIELD, (Settings, "size"))  # as add_config_options records it
    assert default_mismatches(other) == ["toy --size: default 5, Settings.size 4"]


@pytest.mark.parametrize("a, b, same", [(4, 4, True), ([1, 2], (1, 2), True), (0, False, False),
                                        (1.0, 1, True), ("x", "y", False)])
def test_values_compare_as_the_checkers_mean(a, b, same):
    assert _same(a, b) is same
