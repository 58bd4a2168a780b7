"""YAML in and out: reading a config file as plain data, ``--set`` overrides, writing a resolved config."""

from __future__ import annotations

import json
import os
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

import yaml

from ocv2.atomic import atomic_write
from population.config.errors import SET_PREFIX, ConfigError

if TYPE_CHECKING:
    from population.config.schema import Config

#: YAML nodes a config may expand to (aliases included): a config is a few hundred; this stops alias bombs.
MAX_YAML_NODES = 100_000
#: Deepest nesting of lists and mappings: configs and study files nest 4 levels at most. PyYAML builds
#: nodes recursively, so a few KB of ``[[[[...`` would otherwise end in a RecursionError.
MAX_YAML_DEPTH = 64
#: Longest integer literal: every integer a config holds fits int64 (19 digits). Python refuses to parse
#: more than 4,300 digits at all, and a few hundred overflow a float.
MAX_YAML_INT_DIGITS = 100
#: Largest YAML file read: configs and study files are a few KB.
MAX_YAML_BYTES = 4 << 20


_OPENS = (yaml.MappingStartEvent, yaml.SequenceStartEvent)
_CLOSES = (yaml.MappingEndEvent, yaml.SequenceEndEvent)


class _Strict:
    """What ``StrictLoader`` refuses beyond ``yaml.SafeLoader``, for either of PyYAML's parsers."""

    def construct_mapping(self, node, deep=False):
        if isinstance(node, yaml.MappingNode):
            seen = {}
            for key_node, _ in node.value:
                if key_node.tag == "tag:yaml.org,2002:merge":  # `<<: *base` then a key of base: an override
                    continue
                key = self.construct_object(key_node, deep=True)
                try:
                    first = seen.setdefault(key, key_node.start_mark)
                except TypeError:  # an unhashable key: PyYAML's own error names it
                    continue
                if first is not key_node.start_mark:
                    raise yaml.constructor.ConstructorError(
                        None, None, f"duplicate key {key!r} (first at line {first.line + 1})", key_node.start_mark
                    )
        return super().construct_mapping(node, deep=deep)

    def construct_yaml_int(self, node):
        digits = sum(c.isalnum() for c in str(node.value))  # 0x / 0o prefixes count: a bound, not a count
        if digits > MAX_YAML_INT_DIGITS:
            raise yaml.constructor.ConstructorError(
                None, None, f"an integer of {digits} digits (at most {MAX_YAML_INT_DIGITS})", node.start_mark
            )
        _refuse_base_60(node)
        return super().construct_yaml_int(node)

    def construct_yaml_float(self, node):
        _refuse_base_60(node)
        return super().construct_yaml_float(node)


def _refuse_base_60(node) -> None:
    """YAML 1.1 reads ``1:00`` as 60 (base 60, for times): a config holds no times, so it is a typo, said by line."""
    if ":" in str(node.value):
        raise yaml.constructor.ConstructorError(
            None,
            None,
            f"{node.value} reads as a base-60 number in YAML 1.1; write the number, or quote it for a text",
            node.start_mark,
        )


class StrictLoader(_Strict, yaml.SafeLoader):
    """``yaml.SafeLoader`` that refuses what a config must not hold silently or cannot hold at all: a key given
    twice in one mapping (PyYAML keeps the last one), nesting deeper than ``MAX_YAML_DEPTH`` (``check_depth``) and
    integers longer than ``MAX_YAML_INT_DIGITS`` digits. Each is a ``yaml.YAMLError`` with its line."""


# libyaml's parser, which PyPI's PyYAML wheels ship, reads a config about 7 times faster than the pure-Python one
# (every config under configs/: 40 ms instead of 290 ms, the depth check included), and runs, studies and the test
# suite read configs and run directories' config.yaml files over and over. Its error messages are worded and placed
# otherwise ("did not find expected node content at line 2" for a one-line ``[1,``), so a text it refuses is read
# again by the pure-Python parser, whose error is the one reported: the same message as ever, for the price of a
# second read of a text that was wrong anyway.
if yaml.__with_libyaml__:

    class FastStrictLoader(_Strict, yaml.CSafeLoader):
        """``StrictLoader`` on libyaml's parser."""

else:
    FastStrictLoader = None

for _loader in filter(None, (StrictLoader, FastStrictLoader)):
    _loader.add_constructor("tag:yaml.org,2002:int", _loader.construct_yaml_int)
    _loader.add_constructor("tag:yaml.org,2002:float", _loader.construct_yaml_float)


def check_depth(text: str, loader=StrictLoader) -> None:
    """Refuse nesting deeper than ``MAX_YAML_DEPTH`` from the event stream, before any node is built: both PyYAML
    composers build nodes recursively, and a few KB of ``[[[[...`` end the pure-Python one in a RecursionError and
    crash the whole process inside libyaml's (a segmentation fault at 200,000 levels). Events come one at a time, so
    the check stops at the first level too deep."""
    events = loader(text)
    try:
        depth = 0
        while events.check_event():
            event = events.get_event()
            if isinstance(event, yaml.DocumentEndEvent):
                return  # a second document is never composed: the loader refuses it as it reads its start
            # every node counts, as PyYAML's composer counts its recursion: a scalar inside 64 lists is too deep
            if isinstance(event, (*_OPENS, yaml.ScalarEvent, yaml.AliasEvent)) and depth + 1 > MAX_YAML_DEPTH:
                raise yaml.composer.ComposerError(
                    None, None, f"nested deeper than {MAX_YAML_DEPTH} levels", event.start_mark
                )
            if isinstance(event, _OPENS):
                depth += 1
            elif isinstance(event, _CLOSES):
                depth -= 1
    finally:
        events.dispose()


def load_yaml_text(text: str) -> Any:
    """``yaml.safe_load(text)`` through ``StrictLoader``: every YAML text ocv2 reads goes through it."""
    # libyaml takes a tab as a separator where PyYAML's parser refuses it ("a:\t1"): such a text goes to the
    # pure-Python parser, so that what a config may hold does not depend on whether PyYAML has libyaml.
    if FastStrictLoader is not None and "\t" not in text:
        try:
            return _load(text, FastStrictLoader)
        except (yaml.YAMLError, UnicodeError):  # UnicodeError: a lone surrogate, which libyaml cannot encode
            pass  # worded by the pure-Python parser below
    return _load(text, StrictLoader)


def _load(text: str, loader_class) -> Any:
    check_depth(text, loader_class)
    loader = loader_class(text)
    try:
        return loader.get_single_data()
    finally:
        loader.dispose()


def read_yaml(path: str) -> Any:
    """The plain data (mappings, lists, strings, numbers, booleans, null) of a YAML file, or a ConfigError."""
    if os.path.isdir(path):
        raise ConfigError(f"{path}: is a directory, not a config file")
    try:
        with open(path, encoding="utf-8") as handle:
            text = handle.read(MAX_YAML_BYTES + 1)
        if len(text) > MAX_YAML_BYTES:
            raise ConfigError(f"{path}: larger than {MAX_YAML_BYTES >> 20} MiB; not a config file")
        raw = load_yaml_text(text)
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such config file") from None
    except UnicodeDecodeError:
        raise ConfigError(f"{path}: not a text file (not valid UTF-8)") from None
    except OSError as error:
        raise ConfigError(f"{path}: cannot read: {error.strerror or error}") from None
    except yaml.YAMLError as error:
        raise ConfigError(f"{path}: not valid YAML: {yaml_problem(error)}") from None
    try:
        check_plain_data(raw)
    except ConfigError as error:
        raise error.prefixed(path) from None
    return raw


def yaml_problem(error: yaml.YAMLError) -> str:
    """A YAML error as one line: what went wrong and where (PyYAML's own message spans several lines)."""
    mark = getattr(error, "problem_mark", None)
    problem = getattr(error, "problem", None) or str(error).splitlines()[0]
    where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
    return f"{problem}{where}"


def check_plain_data(value, where: str = "") -> None:
    """Refuse what YAML can express but a config cannot hold: dates, binary, sets, self-referencing
    anchors, and alias chains that expand to more than ``MAX_YAML_NODES`` nodes."""
    budget = [MAX_YAML_NODES]

    def walk(node, key: str, parents: tuple[int, ...]) -> None:
        budget[0] -= 1
        if budget[0] < 0:
            raise ConfigError(
                f"the YAML expands to more than {MAX_YAML_NODES} values (anchors and aliases repeated too often)"
            )
        name = key or "the config"
        if isinstance(node, (dict, list)):
            if id(node) in parents:
                raise ConfigError(f"{name}: refers to itself through a YAML anchor")
            inner = (*parents, id(node))
            items = node.items() if isinstance(node, dict) else enumerate(node)
            for child_key, child in items:
                if isinstance(node, dict) and not isinstance(child_key, str):
                    raise ConfigError(f"{name}: key {child_key!r} is not a string")
                child_name = (
                    f"{key}.{child_key}"
                    if isinstance(node, dict) and key
                    else (str(child_key) if isinstance(node, dict) else f"{name}[{child_key}]")
                )
                walk(child, child_name, inner)
            return
        if node is None or isinstance(node, (bool, int, float, str)):
            return
        kind = {
            "date": "a date",
            "datetime": "a date and time",
            "bytes": "binary data (!!binary)",
            "set": "a set (!!set)",
        }.get(type(node).__name__, f"a {type(node).__name__}")
        hint = "; quote it to make it a string" if type(node).__name__ in ("date", "datetime") else ""
        raise ConfigError(f"{name}: {kind} is not a config value, got {node!r}{hint}")

    walk(value, where, ())


def apply_overrides(raw: Mapping, overrides: Sequence[str]) -> dict:
    """``["ppo.lr=1e-3", "env.layout=coord_ring"]`` -> a new nested dict; values are parsed as YAML.

    Errors name the override as the user typed it (``--set ppo.lr=[1,: ...``), never the file.
    """
    data = json.loads(json.dumps(raw))  # deep copy of plain data
    for item in overrides:
        where = f"{SET_PREFIX}{item}"
        if "=" not in item:
            raise ConfigError(f"{where}: expected section.key=value")
        dotted, text = item.split("=", 1)
        parts = dotted.strip().split(".")
        if len(parts) < 2 or not all(parts):
            raise ConfigError(f"{where}: expected section.key=value")
        if len(parts) > MAX_YAML_DEPTH:
            raise ConfigError(f"{where}: a key nested deeper than {MAX_YAML_DEPTH} levels")
        node = data
        for part in parts[:-1]:
            if node.get(part) is None:  # absent, or written as an empty section ("env:" with nothing under it)
                node[part] = {}
            node = node[part]
            if not isinstance(node, dict):
                raise ConfigError(f"{where}: {part} is not a section")
        try:
            value = load_yaml_text(text) if text.strip() else None
        except yaml.YAMLError as error:
            raise ConfigError(f"{where}: the value is not valid YAML: {yaml_problem(error)}") from None
        try:
            check_plain_data(value, dotted.strip())
        except ConfigError as error:
            raise ConfigError([f"{where}: {problem}" for problem in error.problems]) from None
        node[parts[-1]] = value
    return data


def dump_config(config: Config, path: str | os.PathLike) -> None:
    """Write the resolved config as YAML (atomically)."""
    atomic_write(path, yaml.safe_dump(config.to_dict(), sort_keys=False))
