"""What a config field may hold, and how YAML text becomes values (used by tisem/config.py).

A rule checks one value and returns it in the field's type, or raises a one-line
`ConfigError` naming the key, the value and what is allowed:

    Number(float, 0.0, 1e6, low_open=True).check("sigma0", "abc", "--set")
    # ConfigError: --set: sigma0 = 'abc': not a number; expected a number > 0 and <= 1e+06
"""

from __future__ import annotations

import difflib
import math
import os
import re
from dataclasses import dataclass
from pathlib import Path

import yaml

from tisem.errors import ConfigError

MODES = ("st", "adaptive", "spatial", "bki", "csm")
INPUTS = ("predictions", "labels")
QUERY_BLENDS = ("missing", "off")
# the classes whose evidence keeps a short kernel by default (MapperConfig.thin_classes)
THIN_CLASSES = (
    "pole",
    "traffic-sign",
    "trunk",
    "person",
    "bicycle",
    "bicyclist",
    "motorcycle",
    "motorcyclist",
)
# the classes whose evidence reaches at most MapperConfig.vehicle_cap_m by default
VEHICLE_CLASSES = ("car",)
# kernels/bki.py and kernels/training.py keep the classes a training voxel has evidence for as
# the bits of an int32 (a literal 1 << 31 overflows it), and unroll their per-class loops:
# 31 classes at most
MAX_CLASSES = 31


def unknown_name(what: str, name: str, known) -> str:
    """ "unknown key 'tau_ss' (did you mean tau_s?); known: ..." for a name not among `known`."""
    near = difflib.get_close_matches(str(name), list(known), n=2, cutoff=0.7)
    hint = f" (did you mean {' or '.join(near)}?)" if near else ""
    return f"unknown {what} {name!r}{hint}; known: {', '.join(known)}"


def _prefix(where: str, key: str, value) -> str:
    shown = repr(value) if isinstance(value, str) else str(value)
    return f"{where + ': ' if where else ''}{key} = {shown}"


@dataclass(frozen=True)
class Number:
    """An int or float field in [low, high] (either end open when said), always finite."""

    kind: type
    low: float
    high: float
    low_open: bool = False
    high_open: bool = False
    unit: str = ""
    optional: bool = False  # None allowed (e.g. `last`: no end)

    def allowed(self) -> str:
        what = "a whole number" if self.kind is int else "a number"
        low = f"{'>' if self.low_open else '>='} {self.low:g}"
        high = f"{'<' if self.high_open else '<='} {self.high:g}"
        unit = f" ({self.unit})" if self.unit else ""
        none = " or null" if self.optional else ""
        return f"{what} {low} and {high}{unit}{none}"

    def check(self, key: str, value, where: str = ""):
        if value is None and self.optional:
            return None
        said = _prefix(where, key, value)
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            hint = ""
            if isinstance(value, str) and _looks_numeric(value):
                hint = " (a quoted string: write the number without quotes)"
            raise ConfigError(f"{said}: not a number{hint}; expected {self.allowed()}")
        if isinstance(value, float) and not math.isfinite(value):
            raise ConfigError(f"{said}: not a finite number; expected {self.allowed()}")
        if self.kind is int and isinstance(value, float):
            if not value.is_integer():
                raise ConfigError(f"{said}: not a whole number; expected {self.allowed()}")
            value = int(value)
        too_low = value < self.low or (self.low_open and value == self.low)
        too_high = value > self.high or (self.high_open and value == self.high)
        if too_low or too_high:
            raise ConfigError(f"{said}: out of range; expected {self.allowed()}")
        return int(value) if self.kind is int else float(value)


@dataclass(frozen=True)
class Choice:
    """One of a few words. `off_word`: the option that YAML's `off` means (YAML 1.1 reads an
    unquoted off, no or false as the boolean false)."""

    options: tuple[str, ...]
    off_word: str | None = None

    def check(self, key: str, value, where: str = ""):
        if value is False and self.off_word is not None:
            return self.off_word
        if not isinstance(value, str) or value not in self.options:
            raise ConfigError(
                f"{_prefix(where, key, value)}: expected one of {', '.join(self.options)}"
            )
        return value


@dataclass(frozen=True)
class ClassNames:
    """A list of distinct class names: SemanticKITTI's (tisem.labels.CLASS_NAMES) or the active
    label space's, not unlabeled."""

    def check(self, key: str, value, where: str = ""):
        from tisem.labels import CLASS_NAMES, class_names

        known = CLASS_NAMES[1:] + tuple(n for n in class_names()[1:] if n not in CLASS_NAMES)
        if not isinstance(value, (list, tuple)) or not all(isinstance(v, str) for v in value):
            raise ConfigError(
                f"{_prefix(where, key, value)}: expected a list of class names, "
                f"e.g. [pole, trunk] or []"
            )
        for name in value:
            if name not in known:
                raise ConfigError(
                    f"{_prefix(where, key, list(value))}: {unknown_name('class', name, known)}"
                )
        if len(set(value)) != len(value):
            raise ConfigError(f"{_prefix(where, key, list(value))}: a class is named twice")
        return list(value)


@dataclass(frozen=True)
class Flag:
    """true or false."""

    def check(self, key: str, value, where: str = ""):
        if not isinstance(value, bool):
            raise ConfigError(f"{_prefix(where, key, value)}: expected true or false")
        return value


@dataclass(frozen=True)
class Folder:
    """An existing, writable folder on this machine, or null (the system's temp folder)."""

    def check(self, key: str, value, where: str = ""):
        if value is None:
            return None
        if not isinstance(value, (str, os.PathLike)) or not str(value):
            raise ConfigError(f"{_prefix(where, key, value)}: expected a folder path or null")
        path = os.fspath(value)
        said = _prefix(where, key, path)
        if not os.path.isdir(path):
            what = "is not a folder" if os.path.exists(path) else "does not exist"
            raise ConfigError(
                f"{said}: {what}; expected an existing folder (or null: the system's temp folder)"
            )
        if not os.access(path, os.W_OK | os.X_OK):
            raise ConfigError(f"{said}: the folder is not writable")
        return path


def check_fields(obj, rules: dict) -> None:
    """Every field of the dataclass `obj` against its rule (None: a section, checked apart),
    normalising the values (ints where whole numbers belong, floats where numbers do)."""
    for key, rule in rules.items():
        if rule is not None:
            setattr(obj, key, rule.check(key, getattr(obj, key)))


# --------------------------------------------------------------------------- YAML text


class _Loader(yaml.SafeLoader):
    """Safe YAML with YAML 1.2 floats: `1e-4` and `1E5` are numbers (YAML 1.1 wants a dot)."""


_Loader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:[0-9][0-9_]*(?:\.[0-9_]*)?|\.[0-9_]+)[eE][-+]?[0-9]+$"),
    list("-+0123456789."),
)

_NUMBER = re.compile(r"^\s*[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?\s*$")


def _looks_numeric(text: str) -> bool:
    return bool(_NUMBER.match(text)) or text.strip().lower() in ("nan", "inf", "-inf")


def _yaml_problem(exc: yaml.YAMLError) -> str:
    """One line for a YAML error: what is wrong and where (line, column)."""
    mark = getattr(exc, "problem_mark", None) or getattr(exc, "context_mark", None)
    problem = getattr(exc, "problem", None) or str(exc)
    where = f" (line {mark.line + 1}, column {mark.column + 1})" if mark is not None else ""
    return " ".join(f"{problem}{where}".split())


def yaml_value(text: str, where: str):
    """One `--set` value read as YAML (numbers, true/false, null, words)."""
    try:
        return yaml.load(text, Loader=_Loader)
    except yaml.YAMLError as exc:
        raise ConfigError(f"{where}: not a YAML value: {_yaml_problem(exc)}") from None


def read_yaml(path: str | os.PathLike) -> dict:
    """A config file as a dict ({} when empty); ConfigError for a missing or unreadable file,
    bad YAML, an unsafe tag, or a top level that is not a mapping."""
    path = Path(path)
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
        raise ConfigError(f"{path}: cannot read the config file: {reason}") from None
    try:
        data = yaml.load(text, Loader=_Loader)
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: not valid YAML: {_yaml_problem(exc)}") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(
            f"{path}: expected a mapping of config keys at the top level, got {type(data).__name__}"
        )
    return data
