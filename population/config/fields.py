"""One section's mapping -> its typed dataclass: unknown keys (with the nearest valid one), wrong types,
and numbers the arrays they go into cannot hold."""

from __future__ import annotations

import dataclasses
import difflib
import math
import types
import typing
from collections.abc import Mapping
from typing import Any

import numpy as np

from population.config.errors import ConfigError
from population.config.schema import PopulationConfig, PPOConfig

INT32 = (-(2**31), 2**31 - 1)
INT64 = (-(2**63), 2**63 - 1)
#: float32's largest finite value: parameters, learning rates and coefficients are float32 in JAX.
FLOAT32_MAX = float(np.finfo(np.float32).max)
#: Integer fields that never enter a JAX array (held by Python, or checked against a narrower range
#: later); every other integer is a shape, a count or a step number in an int32 array.
INT64_FIELDS = frozenset({(PPOConfig, "rew_shaping_horizon"), (PopulationConfig, "seed")})


def nearest(word: str, choices, prefix: str = "") -> str:
    """ "; did you mean PREFIX.X?" for the closest of ``choices`` to ``word`` (empty if none is close)."""
    close = difflib.get_close_matches(str(word), [str(c) for c in choices], n=1)
    return f"; did you mean {prefix}{'.' * bool(prefix)}{close[0]}?" if close else ""


def parse_section(name: str, cls, raw) -> Any:
    """``raw`` (a mapping or None) as a ``cls``; a ConfigError lists every bad key, with ``partial`` the
    section with those keys at their defaults."""
    if raw is None:
        return cls()
    if not isinstance(raw, Mapping):
        raise ConfigError(f"{name}: expected a mapping of keys, got {type(raw).__name__}")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    hints = typing.get_type_hints(cls)
    values, problems = {}, []
    for key, value in raw.items():
        if key not in fields:
            problems.append(f"{name}.{key}: unknown key{nearest(key, fields, name)} (valid keys: {', '.join(fields)})")
            continue
        bounds = INT64 if (cls, key) in INT64_FIELDS else INT32
        try:
            values[key] = coerce(f"{name}.{key}", value, hints[key], bounds)
        except ConfigError as error:
            problems.extend(error.problems)
    if problems:
        raise ConfigError(problems, partial=cls(**values))
    return cls(**values)


def coerce(key: str, value, hint, bounds: tuple[int, int] = INT32):
    """Check ``value`` against a field's type; ints given as 1e7 floats are accepted when integral."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        errors = []
        for option in (a for a in args if a is not type(None)):  # the first that takes the value, e.g.
            try:  # cluster.num_gpus: float | str, a number or "auto" (its value is checked in validate)
                return coerce(key, value, option, bounds)
            except ConfigError as error:
                errors.append(error)
        raise errors[0]
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{key}: expected a list, got {value!r}")
        return tuple(coerce(f"{key}[{i}]", v, args[0], bounds) for i, v in enumerate(value))
    if hint is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{key}: expected true or false, got {value!r}")
        return value
    if hint is int:
        return bounded_int(key, _integer(key, value), bounds)
    if hint is float:
        return finite_float32(key, _number(key, value))
    if hint is str:
        if isinstance(value, bool) or not isinstance(value, (str, int)):
            raise ConfigError(f"{key}: expected a string, got {value!r}")
        return str(value)
    return value


def integral(value) -> int | None:
    """``value`` as an int when it is one in any form YAML gives: an int, an integral float (1e7 written with a
    dot), or a numeric string (1e7 without one, which YAML reads as a string); None otherwise (bools included)."""
    if isinstance(value, bool):
        return None
    if isinstance(value, int):
        return value
    if isinstance(value, str):
        if not value.isascii():  # float() reads other scripts' digits ("٤٠" is 40): a config's numbers are ASCII
            return None
        try:
            value = float(value)
        except ValueError:
            return None
    if isinstance(value, float) and value.is_integer():
        return int(value)
    return None


def _integer(key: str, value) -> int:
    number = integral(value)
    if number is None:
        raise ConfigError(f"{key}: expected an integer, got {value!r}")
    return number


def _number(key: str, value) -> float:
    if isinstance(value, str) and value.isascii():  # float() reads other scripts' digits too: "٠.٠٠١" is 0.001
        try:
            value = float(value)  # YAML reads "1e-4" (no dot) as a string
        except ValueError:
            pass
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ConfigError(f"{key}: expected a number, got {value!r}")
    if isinstance(value, int) and abs(value) > FLOAT32_MAX:  # float() of a huge int raises OverflowError
        raise ConfigError(f"{key}: {value} is outside float32's range (|x| <= {FLOAT32_MAX:.4g})")
    return float(value)


def bounded_int(key: str, value: int, bounds: tuple[int, int] = INT32) -> int:
    """``value`` if it fits ``bounds`` (int32 for what goes into arrays), else a ConfigError."""
    low, high = bounds
    if not low <= value <= high:
        kind = "int32" if bounds == INT32 else "int64"
        raise ConfigError(f"{key}: {value:.4g} does not fit the {kind} it is stored in ({low} to {high})")
    return value


def finite_float32(key: str, value: float) -> float:
    """``value`` if it is finite and float32 holds it without overflowing or rounding to 0."""
    # A NaN learning rate would "train" to NaN parameters without a word; 1e308 is finite in float64
    # but inf in the float32 the optimiser computes in.
    if not math.isfinite(value):
        raise ConfigError(f"{key}: expected a finite number, got {value!r}")
    if abs(value) > FLOAT32_MAX:
        raise ConfigError(
            f"{key}: {value:.4g} is outside float32's range (|x| <= {FLOAT32_MAX:.4g}), the precision training runs in"
        )
    if value != 0 and np.float32(value) == 0:
        raise ConfigError(f"{key}: {value:.4g} rounds to 0 in float32, the precision training runs in")
    return value
