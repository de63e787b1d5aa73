"""Checks for configuration input, each raising :class:`ConfigError` that names the field.

The ``where`` argument is a dotted path such as ``'table1.yaml: links[1].mass'`` so that the
message tells the user which file, which key and what was expected.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from haptic_topology.errors import ConfigError


def load_yaml(path: str | Path, error: type[ConfigError] = ConfigError) -> dict[str, Any]:
    """Read a YAML mapping from ``path``; missing files and syntax errors raise ``error``."""
    p = Path(path)
    try:
        text = p.read_text(encoding='utf-8')
    except FileNotFoundError:
        raise error(f'{p}: file not found') from None
    except OSError as exc:
        raise error(f'{p}: cannot read ({exc.strerror})') from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, 'problem_mark', None)
        at = f' at line {mark.line + 1}, column {mark.column + 1}' if mark is not None else ''
        problem = getattr(exc, 'problem', None) or str(exc)
        raise error(f'{p}: YAML syntax error{at}: {problem}') from None
    if not isinstance(data, dict):
        raise error(f'{p}: expected a YAML mapping at the top level, got {type(data).__name__}')
    return data


def check_keys(
    mapping: Any,
    where: str,
    required: Sequence[str] = (),
    optional: Sequence[str] = (),
    error: type[ConfigError] = ConfigError,
) -> Mapping[str, Any]:
    """Require ``mapping`` to be a dict holding all ``required`` keys and no unknown ones."""
    if not isinstance(mapping, Mapping):
        raise error(f'{where}: expected a mapping, got {type(mapping).__name__}')
    allowed = set(required) | set(optional)
    for key in mapping:
        if key not in allowed:
            raise error(
                f'{where}.{key}: unknown key (expected one of: {", ".join(sorted(allowed))})')
    for key in required:
        if key not in mapping:
            raise error(f'{where}.{key}: missing required key')
    return mapping


def as_float(
    value: Any,
    where: str,
    lo: float | None = None,
    hi: float | None = None,
    lo_open: bool = False,
    error: type[ConfigError] = ConfigError,
) -> float:
    """Convert ``value`` to a finite float within ``[lo, hi]`` (``(lo, hi]`` if lo_open)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise error(f'{where}: expected a number, got {value!r}')
    x = float(value)
    if not math.isfinite(x):
        raise error(f'{where}: expected a finite number, got {value!r}')
    if lo is not None and (x <= lo if lo_open else x < lo):
        bound = '>' if lo_open else '>='
        raise error(f'{where}: expected a value {bound} {lo}, got {x}')
    if hi is not None and x > hi:
        raise error(f'{where}: expected a value <= {hi}, got {x}')
    return x


def as_int(value: Any, where: str, lo: int | None = None, hi: int | None = None,
           error: type[ConfigError] = ConfigError) -> int:
    """Convert ``value`` to an int within ``[lo, hi]``."""
    if isinstance(value, bool) or not isinstance(value, int):
        raise error(f'{where}: expected an integer, got {value!r}')
    if lo is not None and value < lo:
        raise error(f'{where}: expected an integer >= {lo}, got {value}')
    if hi is not None and value > hi:
        raise error(f'{where}: expected an integer <= {hi}, got {value}')
    return value


def as_str(value: Any, where: str, choices: Sequence[str] | None = None,
           error: type[ConfigError] = ConfigError) -> str:
    """Require a string, optionally one of ``choices``."""
    if not isinstance(value, str):
        raise error(f'{where}: expected a string, got {value!r}')
    if choices is not None and value not in choices:
        raise error(f'{where}: expected one of {", ".join(choices)}, got {value!r}')
    return value


def as_bool(value: Any, where: str, error: type[ConfigError] = ConfigError) -> bool:
    """Require a YAML boolean."""
    if not isinstance(value, bool):
        raise error(f'{where}: expected true or false, got {value!r}')
    return value


def as_vector(
    value: Any,
    where: str,
    size: int | None = None,
    lo: float | None = None,
    lo_open: bool = False,
    error: type[ConfigError] = ConfigError,
) -> np.ndarray:
    """Convert a list of numbers to a float64 vector of length ``size`` (any if None)."""
    if isinstance(value, (int, float)) and not isinstance(value, bool) and size == 1:
        value = [value]
    if not isinstance(value, (list, tuple)):
        expected = f'a list of {size} numbers' if size is not None else 'a list of numbers'
        raise error(f'{where}: expected {expected}, got {value!r}')
    if size is not None and len(value) != size:
        raise error(f'{where}: expected {size} numbers, got {len(value)}')
    return np.array([as_float(v, f'{where}[{i}]', lo=lo, lo_open=lo_open, error=error)
                     for i, v in enumerate(value)], dtype=float)


_PI_EXPR = re.compile(r'^\s*([+-])?\s*(\d+(?:\.\d*)?)?\s*\*?\s*pi\s*(?:/\s*(\d+(?:\.\d*)?))?\s*$')


def as_angles(value: Any, where: str, size: int,
              error: type[ConfigError] = ConfigError) -> np.ndarray:
    """A list of ``size`` numbers or strings like ``-pi/4``, ``2*pi/3`` as a float64 vector."""
    if not isinstance(value, list):
        raise error(f'{where}: expected a list of {size} numbers, got {value!r}')
    out = []
    for i, v in enumerate(value):
        if isinstance(v, str):
            m = _PI_EXPR.match(v)
            if m is None:
                raise error(f'{where}[{i}]: expected a number or an expression like '
                            f'-pi/4, got {v!r}')
            sign = -1.0 if m.group(1) == '-' else 1.0
            factor = float(m.group(2)) if m.group(2) else 1.0
            div = float(m.group(3)) if m.group(3) else 1.0
            if div == 0.0:
                raise error(f'{where}[{i}]: division by zero in {v!r}')
            out.append(sign * factor * math.pi / div)
        else:
            out.append(as_float(v, f'{where}[{i}]', error=error))
    if len(out) != size:
        raise error(f'{where}: expected {size} numbers, got {len(out)}')
    return np.array(out)
