"""Checks at n2f2's boundaries, written once: numbers read from files must be finite, numeric
command-line options must make sense, an optimisation whose steps keep going non-finite stops,
and nothing non-finite is ever saved.

* :func:`finite_array`: an array read from a user's file; a NaN or infinite value is an
  :class:`~n2f2.errors.InputError` naming the file and the first bad row.
* Option types for argparse (``type=positive_int`` ...): they reject NaN, infinity and values
  that mean nothing for the option (a zero step count, a negative weight) with argparse's own
  error, one line and exit status 2 through :class:`OneLineArgumentParser`. Each carries
  ``invalid_examples``: values it must refuse, which the test suite feeds to every option.
* :data:`MAX_BAD_STEPS` and :class:`NonFiniteError`: training and fitting skip a step whose
  loss or gradient is not finite, and stop with this error after that many in a row.
  :func:`check_finite` refuses to save a checkpoint, field or PLY holding NaN or infinity.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import Any, Callable, Optional

import numpy as np

from .errors import InputError, N2F2Error

# Consecutive non-finite optimisation steps (loss or gradient NaN / infinite) after which train
# and fit-gaussians stop: single bad steps are skipped, a run of them means the inputs or the
# settings are broken and further steps would only waste time.
MAX_BAD_STEPS = 20


class NonFiniteError(N2F2Error, ValueError):
    """An optimisation went non-finite, or a result about to be saved holds NaN or infinity."""

    def __init__(self, path: str | Path | None, problem: str):
        self.path = None if path is None else Path(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}" if self.path is not None else problem)


# ----------------------------------------------------------------------------- arrays
def finite_array(path: str | Path | None, name: str, arr: Any) -> np.ndarray:
    """``arr`` as an array when every value is finite; otherwise an :class:`InputError` on
    ``path`` naming the first bad row of ``name`` (e.g. "row 17 of frame_00003_f.npy is not
    finite (2 rows are)"). Integer and boolean arrays are always finite."""
    a = np.asarray(arr)
    if a.dtype.kind not in "fc" or a.size == 0:
        return a
    bad = ~np.isfinite(a)
    if not bad.any():
        return a
    if a.ndim == 0:
        raise InputError(path, f"{name} is not finite ({a.item()})")
    rows = np.flatnonzero(bad.reshape(a.shape[0], -1).any(axis=1))
    unit = "row" if a.ndim >= 2 else "entry"
    more = f" ({rows.size} {unit}s are)" if rows.size > 1 else ""
    raise InputError(path, f"{unit} {int(rows[0])} of {name} is not finite{more}")


def _non_finite(obj: Any, prefix: str = "") -> Optional[str]:
    """The name of the first tensor / array inside ``obj`` (nested dicts, lists, tuples) that
    holds a NaN or infinite value, with how many, or None."""
    import torch

    if isinstance(obj, torch.Tensor):
        if obj.is_floating_point() or obj.is_complex():
            bad = int((~torch.isfinite(obj.detach())).sum())
            if bad:
                return f"{prefix or 'tensor'} ({bad} of {obj.numel()} values)"
        return None
    if isinstance(obj, np.ndarray):
        if obj.dtype.kind in "fc":
            bad = int((~np.isfinite(obj)).sum())
            if bad:
                return f"{prefix or 'array'} ({bad} of {obj.size} values)"
        return None
    if isinstance(obj, float):
        return None if math.isfinite(obj) else (prefix or "value")
    if isinstance(obj, dict):
        items = obj.items()
    elif isinstance(obj, (list, tuple)):
        items = enumerate(obj)
    else:
        return None
    for key, value in items:
        found = _non_finite(value, f"{prefix}[{key!r}]" if prefix else str(key))
        if found:
            return found
    return None


def check_finite(path: str | Path, obj: Any) -> None:
    """Raise :class:`NonFiniteError` naming ``path`` when any tensor or array in ``obj`` (a
    tensor, an array, or dicts / lists of them) holds a NaN or infinite value: called before
    every save of a checkpoint, a field or a PLY."""
    found = _non_finite(obj)
    if found:
        raise NonFiniteError(path, f"refusing to write: {found} are NaN or infinite")


# ----------------------------------------------------------------------------- option types
def _option_type(
    name: str, parse: Callable[[str], Any], ok: Callable[[Any], bool], need: str, invalid: tuple[str, ...]
) -> Callable[[str], Any]:
    def convert(text: str) -> Any:
        try:
            value = parse(text)
        except (TypeError, ValueError, OverflowError):
            value = None
        if value is None or not ok(value):
            raise argparse.ArgumentTypeError(f"must be {need}, got {text!r}")
        return value

    convert.__name__ = name
    convert.__qualname__ = name
    convert.__doc__ = f"argparse type: {need}."
    convert.invalid_examples = invalid  # type: ignore[attr-defined]
    return convert


def _finite(x: float) -> bool:
    return math.isfinite(x)


positive_int = _option_type(
    "positive_int", int, lambda v: v > 0, "a positive integer", ("0", "-1", "nan", "inf", "1.5", "x")
)
nonneg_int = _option_type("nonneg_int", int, lambda v: v >= 0, "an integer >= 0", ("-1", "nan", "inf", "1.5", "x"))
port_number = _option_type(
    "port_number", int, lambda v: 0 <= v <= 65535, "a port number in 0..65535", ("-1", "65536", "nan", "inf", "x")
)
positive_float = _option_type(
    "positive_float",
    float,
    lambda v: _finite(v) and v > 0,
    "a finite number > 0",
    ("0", "-1", "nan", "inf", "-inf", "x"),
)
nonneg_float = _option_type(
    "nonneg_float", float, lambda v: _finite(v) and v >= 0, "a finite number >= 0", ("-1", "nan", "inf", "-inf", "x")
)
finite_float = _option_type("finite_float", float, _finite, "a finite number", ("nan", "inf", "-inf", "x"))
unit_interval = _option_type(
    "unit_interval", float, lambda v: 0.0 <= v <= 1.0, "a number in [0, 1]", ("-0.5", "1.5", "nan", "inf", "x")
)

# Composite temperature (n2f2.query.composite): a positive number, "paper" (T = 1, the paper's
# Eq. 6) or "uniform" (T = infinity, the default).
COMPOSITE_TEMPERATURE_NAMES = {"paper": 1.0, "uniform": math.inf}
composite_temperature = _option_type(
    "composite_temperature",
    lambda text: COMPOSITE_TEMPERATURE_NAMES.get(text.strip().lower(), None) or float(text),
    lambda v: v > 0,  # NaN fails; inf is "uniform"
    "a number > 0, 'paper' (1) or 'uniform' (infinity)",
    ("0", "-1", "nan", "-inf", "x"),
)

OPTION_TYPES = (
    positive_int,
    nonneg_int,
    port_number,
    positive_float,
    nonneg_float,
    finite_float,
    unit_interval,
    composite_temperature,
)


def add_device_option(parser: argparse.ArgumentParser, what: str = "") -> None:
    """``--device``, the same for every command: a torch device, ``cpu`` unless given."""
    parser.add_argument("--device", default="cpu", help=f"torch device{what} (default cpu; e.g. cuda, cuda:1)")


class OneLineArgumentParser(argparse.ArgumentParser):
    """An ``ArgumentParser`` whose errors are one line on stderr and exit status 2, like every
    other n2f2 error: ``n2f2 train: error: --dim must be a positive integer, got '0' (see
    n2f2 train --help)``, without the usage block."""

    def error(self, message: str) -> None:  # type: ignore[override]
        if message.startswith("argument ") and ": must be " in message:
            flag, _, rest = message[len("argument ") :].partition(": ")
            message = f"{flag} {rest}"
        message = " ".join(message.split())
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")
