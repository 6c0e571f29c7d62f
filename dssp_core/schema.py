"""Typed settings files: one validated schema per file kind (numpy-free, torch-free).

Every settings file the toolkit reads (the safety layer, point-cloud settings, recording thresholds,
calibration, run configs, the model manifest's runtime facts) is a frozen or plain dataclass that
subclasses :class:`Settings`. Its fields are declared with :func:`setting`, which records the
physically meaningful range, the unit and the allowed choices:

    @dataclass(frozen=True)
    class SafetyConfig(Settings):
        SECTION = "safety"
        max_joint_step: float = setting(0.05, gt=0, le=0.5, unit="rad per tick")
        disable_on_exit: bool = setting(False)

Construction checks every field against its annotation, strictly — JSON ``"false"`` is not a boolean,
``64.5`` and ``true`` are not integers, NaN and infinity are not numbers — and against its range, and
raises :class:`~dssp_core.errors.ConfigError` with one line naming the field, the value and the range:

    safety.disable_on_exit must be true or false (a JSON boolean), got 'false'

Cross-field rules go in :meth:`Settings.validate`. ``from_dict`` refuses unknown keys (a typo must not be
ignored), ``load`` reads a JSON file and prefixes the error with its path. Why by hand: the standard
library has no validating dataclasses, and a schema library (pydantic) would be a heavy dependency of the
robot's runtime for the dozen checks written here.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import re
import types
import typing
from collections.abc import Mapping
from dataclasses import MISSING, dataclass
from pathlib import Path
from typing import Any, ClassVar

from dssp_core.errors import ConfigError
from dssp_core.files import read_input_bytes

# Bounds shared by the training configs and the model manifest (a model past them is refused on load).
MAX_DIM = 4096  # state / action channels
MAX_WIDTH = 65536
MAX_LAYERS = 256
MAX_STEPS = 4096  # N, H, H_a
MAX_RATE_HZ = 1000.0  # control rate: the Piper's CAN feedback arrives at 200 Hz
MIN_RATE_HZ = 0.1  # control rate: below 0.1 Hz a tick outlasts any sensible timeout
DEFAULT_CONTROL_RATE_HZ = 10.0  # the control rate where neither the data, the model nor --control-rate gives one
CONTROL_RATE_FLAG = "--control-rate"  # every command's option for it (Hz)


def control_rate_setting():
    """A settings field for a control rate that may be unknown (None): the range :func:`check_rate` checks."""
    return setting(None, ge=MIN_RATE_HZ, le=MAX_RATE_HZ, unit="Hz")


def check_rate(rate, flag: str = CONTROL_RATE_FLAG) -> float:
    """``rate`` in [MIN_RATE_HZ, MAX_RATE_HZ] Hz as a float, else a one-line ConfigError naming ``flag`` (the option
    or the field that gave it): the control rates a dataset, a model or a robot may run at."""
    if (
        isinstance(rate, bool)
        or not isinstance(rate, (int, float))
        or not _finite(rate)
        or not MIN_RATE_HZ <= rate <= MAX_RATE_HZ
    ):
        raise ConfigError(f"{flag} must be in [{MIN_RATE_HZ:g}, {MAX_RATE_HZ:g}] Hz, got {rate!r}")
    return float(rate)


_REGISTRY: list[type] = []


@dataclass(frozen=True)
class Spec:
    """What a field accepts beyond its type: bounds (ge/gt/le/lt), unit, choices, sequence length."""

    ge: float | None = None
    gt: float | None = None
    le: float | None = None
    lt: float | None = None
    unit: str = ""
    choices: tuple | None = None
    min_length: int | None = None
    max_length: int | None = None

    def range_text(self) -> str:
        low = f"[{_num(self.ge)}" if self.ge is not None else (f"({_num(self.gt)}" if self.gt is not None else None)
        high = f"{_num(self.le)}]" if self.le is not None else (f"{_num(self.lt)})" if self.lt is not None else None)
        unit = f" {self.unit}" if self.unit else ""
        if low and high:
            return f" in {low}, {high}{unit}"
        if low:
            return f" {'>=' if low[0] == '[' else '>'} {low[1:]}{unit}"
        if high:
            return f" {'<=' if high[-1] == ']' else '<'} {high[:-1]}{unit}"
        return f" ({self.unit})" if self.unit else ""

    def in_range(self, v: float) -> bool:
        return not (
            (self.ge is not None and v < self.ge)
            or (self.gt is not None and v <= self.gt)
            or (self.le is not None and v > self.le)
            or (self.lt is not None and v >= self.lt)
        )


def _num(v: float) -> str:
    return f"{v:g}" if isinstance(v, float) else str(v)


def setting(
    default: Any = MISSING,
    *,
    default_factory: Any = MISSING,
    ge=None,
    gt=None,
    le=None,
    lt=None,
    unit: str = "",
    choices=None,
    min_length: int | None = None,
    max_length: int | None = None,
):
    """A dataclass field with its range, unit and choices (see the module docstring)."""
    spec = Spec(ge, gt, le, lt, unit, tuple(choices) if choices is not None else None, min_length, max_length)
    return dataclasses.field(default=default, default_factory=default_factory, metadata={"spec": spec})


class Settings:
    """Mixin for settings dataclasses: strict type/range checks on construction, JSON in and out."""

    SECTION: ClassVar[str] = "settings"

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        _REGISTRY.append(cls)

    def __post_init__(self) -> None:
        hints = _type_hints(type(self))
        for f in dataclasses.fields(self):
            spec = f.metadata.get("spec", Spec())
            value = check_value(getattr(self, f.name), hints[f.name], spec, f"{self.SECTION}.{f.name}")
            object.__setattr__(self, f.name, value)
        self.validate()

    def validate(self) -> None:
        """Cross-field rules; raise ConfigError. The per-field checks have already passed."""

    @classmethod
    def field_names(cls) -> list[str]:
        return [f.name for f in dataclasses.fields(cls)]

    @classmethod
    def from_dict(cls, values: Mapping[str, Any]):
        """Build from a JSON object; unknown keys and a non-object are one-line ConfigErrors."""
        if not isinstance(values, Mapping):
            raise ConfigError(f"{cls.SECTION} settings must be a JSON object, got {type(values).__name__}")
        known = cls.field_names()
        unknown = sorted(set(values) - set(known))
        if unknown:
            raise ConfigError(
                f"unknown {cls.SECTION} setting(s) {', '.join(map(str, unknown))}; known: {', '.join(known)}"
            )
        missing = [
            f.name
            for f in dataclasses.fields(cls)
            if f.default is MISSING and f.default_factory is MISSING and f.name not in values
        ]
        if missing:
            raise ConfigError(
                f"{cls.SECTION} settings lack {', '.join(missing)}; add {'it' if len(missing) == 1 else 'them'}"
            )
        return cls(**values)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict (tuples become lists, nested settings dicts)."""
        return _jsonable(dataclasses.asdict(self))

    @classmethod
    def load(cls, path: str | Path, what: str | None = None):
        """Read and validate a JSON settings file; every error is one line that starts with the path."""
        values = read_json_object(path, what or f"{cls.SECTION} settings")
        try:
            return cls.from_dict(values)
        except ConfigError as exc:
            raise ConfigError(f"{path}: {exc}") from None


@functools.cache
def _type_hints(cls: type) -> dict[str, Any]:
    """A settings class's resolved annotations, once per class (resolving them on every construction dominated the
    cost of building a settings object)."""
    return typing.get_type_hints(cls)


def all_schemas() -> list[type]:
    """Every Settings dataclass defined so far (import the modules that define them first)."""
    return [c for c in _REGISTRY if dataclasses.is_dataclass(c)]


class DuplicateKey(ValueError):
    """A JSON object names one key twice (json.loads would keep the last silently)."""


def _no_duplicates(pairs: list[tuple[str, Any]]) -> dict:
    out = {}
    for key, value in pairs:
        if key in out:
            raise DuplicateKey(key)
        out[key] = value
    return out


JSON_MAX_DEPTH = 64
"""Nesting a JSON file may have (a settings file nests 3 deep; 64 leaves room and keeps the parser far from
Python's recursion limit)."""

_JSON_TOKENS = re.compile(r'"(?:[^"\\]|\\.)*"|[\[\]{}]')


def json_depth(text: str, limit: int = JSON_MAX_DEPTH) -> int:
    """The deepest nesting of arrays and objects in ``text`` (strings skipped), counted only up to ``limit + 1``:
    the check runs before the parser, which would recurse once per level."""
    depth = deepest = 0
    for match in _JSON_TOKENS.finditer(text):
        token = match.group()
        if token in "[{":
            depth += 1
            if depth > deepest:
                deepest = depth
                if deepest > limit:
                    break
        elif token in "]}":
            depth -= 1
    return deepest


def parse_json(text: str) -> Any:
    """``json.loads`` that refuses a key given twice, and nesting deeper than :data:`JSON_MAX_DEPTH`, as
    ValueErrors."""
    if json_depth(text) > JSON_MAX_DEPTH:  # before the parser, which recurses once per level
        raise ValueError(f"nested more than {JSON_MAX_DEPTH} levels deep")
    return json.loads(text, object_pairs_hook=_no_duplicates)


def read_json(
    path: str | Path, label: str, *, error: type[Exception] = ConfigError, hint: str | None = None, **read
) -> Any:
    """Any JSON value from a file a user names, read through :func:`~dssp_core.files.read_input_bytes` (``read``: its
    ``limit`` and ``follow_links``) and :func:`parse_json`, or one line starting with ``label`` raised as ``error``;
    ``hint`` replaces the generic advice on a file that exists but holds no usable JSON (e.g. how to restore it)."""
    fix = f"; {hint}" if hint else ""
    data = read_input_bytes(path, label, error=error, **read)
    try:
        return parse_json(data.decode())
    except DuplicateKey as exc:
        raise error(f"{label} gives the key {exc} twice; " + (hint or "keep one")) from None
    except UnicodeDecodeError:
        raise error(f"{label} is not a text file" + (f" (damaged?){fix}" if hint else "; give a JSON file")) from None
    except json.JSONDecodeError as exc:
        raise error(f"{label} is not valid JSON ({exc.msg} at line {exc.lineno}){fix}") from None
    except ValueError as exc:
        raise error(f"{label} is not a usable JSON object ({exc}){fix}") from None


def read_json_object(
    path: str | Path, what: str | None, *, error: type[Exception] = ConfigError, hint: str | None = None
) -> dict:
    """A JSON object from a file (:func:`read_json`), or one line naming the file and the problem:
    ``"{what} file {path} ..."`` (``what`` None: ``"{path} ..."``), raised as ``error``."""
    label = f"{what} file {path}" if what else str(path)
    values = read_json(path, label, error=error, hint=hint)
    if not isinstance(values, dict):
        raise error(f"{label} must hold a JSON object, got {type(values).__name__}" + (f"; {hint}" if hint else ""))
    return values


def _jsonable(value: Any) -> Any:
    if isinstance(value, dict):
        return {k: _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    return value


# ---------------------------------------------------------------------------------- the checks
def _fail(name: str, what: str, spec: Spec, value: Any) -> typing.NoReturn:
    raise ConfigError(f"{name} must be {what}{spec.range_text()}, got {_show(value)}")


def _show(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _union_args(tp: Any) -> tuple | None:
    origin = typing.get_origin(tp)
    if origin is typing.Union or (hasattr(types, "UnionType") and origin is types.UnionType):
        return typing.get_args(tp)
    return None


def describe(tp: Any) -> str:
    """Human words for a type annotation: 'a number', 'an integer', 'true or false', ..."""
    args = _union_args(tp)
    if args is not None:
        parts = [describe(a) for a in args if a is not type(None)]
        return " or ".join(parts) + (" or null" if type(None) in args else "")
    if tp is bool:
        return "true or false (a JSON boolean)"
    if tp is int:
        return "an integer"
    if tp is float:
        return "a finite number"
    if tp is str:
        return "a string"
    origin = typing.get_origin(tp)
    if origin in (list, tuple):
        items = typing.get_args(tp)
        if origin is tuple and items and items[-1] is not Ellipsis:
            return f"a list of {len(items)} {_plural(items[0])}"
        return f"a list of {_plural(items[0])}" if items else "a list"
    if dataclasses.is_dataclass(tp):
        return "a JSON object"
    return getattr(tp, "__name__", str(tp))


def _plural(tp: Any) -> str:
    named = {int: "integers", float: "finite numbers", str: "strings", bool: "booleans"}
    if tp in named:
        return named[tp]
    words = describe(tp)
    return words[2:].replace("list ", "lists ", 1) if words.startswith("a list") else words


def _finite(value: int | float) -> bool:
    try:
        return math.isfinite(value)
    except OverflowError:  # an int too large for a float
        return False


def check_value(value: Any, tp: Any, spec: Spec, name: str) -> Any:
    """``value`` checked against the annotation ``tp`` and ``spec``; returns it normalised (float, tuple)."""
    args = _union_args(tp)
    if args is not None:
        if value is None and type(None) in args:
            return None
        rest = [a for a in args if a is not type(None)]
        if len(rest) == 1:
            return check_value(value, rest[0], spec, name)
        for a in rest:
            try:
                return check_value(value, a, spec, name)
            except ConfigError:
                continue
        _fail(name, describe(tp), spec, value)
    if tp is Any:
        return value
    if tp is bool:
        if not isinstance(value, bool):
            _fail(name, describe(bool), Spec(), value)
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            _fail(name, "an integer", spec, value)
        if spec.choices is not None and value not in spec.choices:
            _fail(name, f"one of {', '.join(map(str, spec.choices))}", Spec(unit=spec.unit), value)
        if not spec.in_range(value):
            _fail(name, "an integer", spec, value)
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not _finite(value):
            _fail(name, "a finite number", spec, value)
        if not spec.in_range(value):
            _fail(name, "a number", spec, value)
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            _fail(name, "a string", Spec(), value)
        if spec.choices is not None and value not in spec.choices:
            raise ConfigError(f"{name} must be one of {', '.join(map(repr, spec.choices))}, got {_show(value)}")
        return value
    origin = typing.get_origin(tp)
    if origin in (list, tuple):
        items = typing.get_args(tp)
        fixed = origin is tuple and bool(items) and items[-1] is not Ellipsis
        if not isinstance(value, (list, tuple)):
            _fail(name, describe(tp), Spec(), value)
        if fixed and len(value) != len(items):
            _fail(name, describe(tp), Spec(), value)
        n = len(value)
        if (spec.min_length is not None and n < spec.min_length) or (
            spec.max_length is not None and n > spec.max_length
        ):
            bounds = f"{spec.min_length or 0}..{spec.max_length if spec.max_length is not None else 'any'}"
            raise ConfigError(f"{name} must hold {bounds} values, got {n}: {_show(value)}")
        item_spec = dataclasses.replace(spec, min_length=None, max_length=None)
        checked = [
            check_value(v, items[i] if fixed else (items[0] if items else Any), item_spec, f"{name}[{i}]")
            for i, v in enumerate(value)
        ]
        return tuple(checked) if origin is tuple else checked
    if dataclasses.is_dataclass(tp):
        if isinstance(value, tp):
            return value
        if isinstance(value, Mapping) and issubclass(tp, Settings):
            return tp.from_dict(value)
        _fail(name, "a JSON object", Spec(), value)
    if origin is dict:
        if not isinstance(value, Mapping):
            _fail(name, "a JSON object", Spec(), value)
        return dict(value)
    raise TypeError(f"{name}: the schema cannot check the annotation {tp!r}")
