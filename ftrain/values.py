"""Config values: YAML data converted into the config's dataclasses, amounts of work (a number of iterations, or a
duration such as ``"30s"``, ``"5m"``, ``"1h"``), and ``--storage-option`` words as overrides, with one-line errors
naming the key.

Torch-free, like the config: the supervisor validates a run's config before it launches anything.
"""

from __future__ import annotations

import dataclasses
import math
import re
import types
import typing
from dataclasses import dataclass
from typing import Any

import yaml

from ftrain.errors import UserError, closest
from ftrain.redact import Url

_DURATION = re.compile(r"^\s*(\d+(?:\.\d+)?)\s*(s|m|h)\s*$")
_UNITS = {"s": 1.0, "m": 60.0, "h": 3600.0}


@dataclass(frozen=True)
class Amount:
    """A number of iterations or of seconds (exactly one is set)."""

    iterations: int | None = None
    seconds: float | None = None

    def __str__(self) -> str:
        return f"{self.iterations} iterations" if self.iterations is not None else f"{self.seconds:g} s"

    def exceeded_by(self, iterations: int, seconds: float) -> bool:
        if self.iterations is not None:
            return iterations > self.iterations
        return seconds > self.seconds


def is_whole(value: object, low: int = 0) -> bool:
    """An int of ``low`` or more: not a bool (YAML's and JSON's true is no count) and not a float."""
    return isinstance(value, int) and not isinstance(value, bool) and value >= low


def is_number(value: object) -> bool:
    """A finite int or float, not a bool: what a count or a measure read back from a file may be."""
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


def parse_amount(key: str, value: object, auto: bool = False) -> Amount | None:
    """``value`` of config key ``key``: N iterations, or a duration ``"30s"``, ``"5m"``, ``"1h"``; ``"auto"`` (None)
    where ``auto`` is allowed. UserError otherwise."""
    if is_whole(value, 1):
        return Amount(iterations=value)
    if auto and value == "auto":
        return None
    match = _DURATION.match(value) if isinstance(value, str) else None
    if match and float(match[1]) > 0:
        return Amount(seconds=float(match[1]) * _UNITS[match[2]])
    choices = "a number of iterations (e.g. 100), a duration (e.g. 30s, 5m, 1h)" + (" or auto" if auto else "")
    raise UserError(f"{key}={value!r} must be {choices}")


def parse_value(raw: str) -> Any:
    try:
        return yaml.safe_load(raw)
    except yaml.YAMLError:
        return raw


def set_dotted(data: dict, key: str, value: Any) -> None:
    *parents, leaf = key.split(".")
    node = data
    for part in parents:
        child = node.setdefault(part, {})
        if not isinstance(child, dict):
            raise UserError(f"override {key}: {part!r} is not a section")
        node = child
    node[leaf] = value


def build(cls: type, data: dict, prefix: str) -> Any:
    """Instantiate dataclass ``cls`` from ``data``, converting and checking every value against its type."""
    defaults = {f.name: f.default for f in dataclasses.fields(cls)}
    names = list(defaults)
    if not isinstance(data, dict):
        keys = ", ".join(names[:4]) + (", ..." if len(names) > 4 else "")
        raise UserError(f"{prefix.rstrip('.') or 'config'} must be a mapping of its keys ({keys}), got {data!r}")
    hints = typing.get_type_hints(cls)
    kwargs = {}
    for key, value in data.items():
        if key not in names:
            near = closest(str(key), names, cutoff=0.5)
            hint = f"did you mean {prefix}{near}?" if near else f"valid keys: {', '.join(prefix + n for n in names)}"
            raise UserError(f"unknown config key {prefix}{key}: {hint}")
        default = defaults[key]
        example = default if isinstance(default, (int, float)) and not isinstance(default, bool) else None
        kwargs[key] = convert(hints[key], value, f"{prefix}{key}", example)
    return cls(**kwargs)


def _list_example(item_kind: Any, given: Any) -> str:
    """A list of ``item_kind`` as an override writes it: of the one number ``given``, where that is one."""
    if dataclasses.is_dataclass(item_kind):
        first = dataclasses.fields(item_kind)[0].name
        return f"[{{{first}: ...}}]"
    if item_kind in (int, float) and isinstance(given, item_kind) and not isinstance(given, bool):
        return f"[{given}]"
    return {int: "[64,64]", float: "[0.5,0.5]"}.get(item_kind, "[a,b]")


def convert(kind: Any, value: Any, key: str, example: float | None = None) -> Any:
    """``value`` as ``kind``, else UserError naming ``key``; ``example``: a value to show in it (the default)."""
    e_g = f", e.g. {key}={example if example is not None else 100}"
    origin = typing.get_origin(kind)
    if dataclasses.is_dataclass(kind):
        return build(kind, value if value is not None else {}, f"{key}.")
    if origin is list:
        (item_kind,) = typing.get_args(kind)
        if not isinstance(value, list):
            raise UserError(f"{key}={value!r} must be a list, e.g. {key}={_list_example(item_kind, value)}")
        return [convert(item_kind, item, f"{key}[{i}]") for i, item in enumerate(value)]
    if origin in (typing.Union, types.UnionType):
        return value
    if kind is dict:
        if not isinstance(value, dict):
            raise UserError(f"{key}={value!r} must be a mapping, e.g. {key}={{a: 1}}")
        return value
    if kind is bool:
        if not isinstance(value, bool):
            raise UserError(f"{key}={value!r} must be true or false")
        return value
    if kind is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise UserError(f"{key}={value!r} must be an integer{e_g}")
        return value
    if kind is float:
        if isinstance(value, str):  # YAML 1.1 reads 3e-4 (no dot) as a string
            try:
                return float(value)
            except ValueError:
                pass
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise UserError(f"{key}={value!r} must be a number{e_g}")
        return float(value)
    if kind in (str, Url):
        if value is None:
            value = ""
        if not isinstance(value, (str, int, float)) or isinstance(value, bool):
            raise UserError(f"{key}={value!r} must be a string")
        return kind(value if isinstance(value, str) else str(value))
    return value


STORAGE_OPTION = "--storage-option"


def storage_option_overrides(words: list[str]) -> list[str]:
    """``--storage-option KEY=VALUE`` words as the config overrides ``storage.options.KEY=VALUE``: every command that
    opens a storage reads them as ``ftrain train`` reads its config, and the supervisor hides their credentials as it
    hides any override's. The words are never quoted back: a value may be a secret."""
    for number, word in enumerate(words, 1):
        key, sep, _ = word.partition("=")
        if not sep or not key.strip():
            raise UserError(
                f"{STORAGE_OPTION} number {number} is not KEY=VALUE: write it like {STORAGE_OPTION} "
                "endpoint_url=http://127.0.0.1:9000"
            )
    return [f"storage.options.{word.strip()}" for word in words]


def dotted(data: dict, prefix: str = "") -> dict[str, object]:
    """A nested config dict by dotted key, ``{"a": {"b": 1}}`` -> ``{"a.b": 1}``; lists and empty dicts are values."""
    leaves: dict[str, object] = {}
    for key, value in data.items():
        if isinstance(value, dict) and value:
            leaves.update(dotted(value, f"{prefix}{key}."))
        else:
            leaves[f"{prefix}{key}"] = value
    return leaves
