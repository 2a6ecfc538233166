"""One typed schema for every method option: dataclass fields carry their own type, range and help.

The pipeline's :class:`~swiftjax.pipeline.PipelineConfig` declares each field with
:func:`option`; from that single declaration come

* validation (:func:`validate`, called by the dataclass's ``__post_init__``: a config that
  exists is a valid config, whether it was built in Python, from TOML or from flags),
* the command-line flags (:func:`add_arguments`: ``--chunk-size``, ``--[no-]loop-closure``,
  with the default, the allowed range or choices and a description in ``--help``),
* TOML parsing (:func:`from_sources`: typed values only -- no truthy strings),
* the stage each option belongs to (``metadata["stage"]``), from which the run directory
  derives per-stage fingerprints (an export-only option never invalidates predictions).

The stage option classes (``AlignOptions``, ``GraphOptions``, ``LoopOptions``,
``VerificationConfig``) declare their fields with :func:`option` too, without ``stage`` (a
stage class belongs to one stage as a whole; ``stage`` is the pipeline's fingerprint key and
only :class:`~swiftjax.pipeline.PipelineConfig` gives it).  A ``PipelineConfig`` field that
feeds a stage option is declared by it: ``option(target=(StageClass, "field"), stage=...)``
takes the stage field's default, help, range and choices (a keyword given beside ``target``
may only narrow them or set the pipeline's own default).  :func:`build` makes any stage
options object from a config through those targets (nested stage objects, such as
``LoopOptions.verification_config``, declared with :func:`nested`, are built the same way),
and :class:`built` makes it an attribute (``config.loops``).
:func:`replace` is the one ``replace``: a validated copy, ``None`` a value like any other.

Adding an option is one line in the dataclass::

    voxel_size: float | None = option(None, "voxel edge for per-chunk downsampling of the cloud",
                                      low=0.0, low_open=True, optional=True, stage="export")

Rules (every violation is an :class:`OptionError`, one line naming the option first --
``Class.field``, a flag, or a TOML key and its file -- then the value and what is allowed:
``"LoopOptions.top_k: 0 is out of range; allowed: ..."``; the CLI prints it and exits with
status 2):

* ``bool`` options take ``true``/``false`` (TOML booleans, or the ``--x``/``--no-x`` flags):
  the string ``"no"`` or the number ``1`` is refused, never read as truthy;
* ``int`` options take integers only: ``60.7``, ``60.0``, ``true`` and ``1e400`` are refused;
* ``float`` options take integers or floats, finite unless ``finite=False`` (``nan``, ``inf``,
  ``1e400`` refused), converted to ``float`` (so ``1`` and ``1.0`` are the same configuration);
* ``str`` options with ``choices`` take one of them, exactly;
* ``optional=True`` options also take ``None``, spelt ``none`` on the command line and
  ``"none"`` in TOML (which has no null);
* ranges are ``low <= x <= high`` (``low_open``/``high_open`` make them strict).

Cross-option rules (``overlap < chunk_size``, ...) stay in the dataclass's ``__post_init__``.
"""

from __future__ import annotations

import argparse
import dataclasses
import difflib
import math
import numbers
import re
from collections.abc import Iterable, Mapping
from typing import Any, Generic, TypeVar, overload

from swiftjax.errors import SwiftjaxError

__all__ = [
    "OptionError",
    "Spec",
    "STAGES",
    "option",
    "spec",
    "specs",
    "validate",
    "coerce",
    "from_sources",
    "add_arguments",
    "flag",
    "stage_options",
    "nested",
    "replace",
    "invalid",
    "build",
    "built",
    "targets",
    "INT_LIMIT",
]

#: The stages of a run in order; an option's stage is the first one whose result it changes.
#: "temporal": chunk predictions, their stored export points and the temporal edges;
#: "loops": loop detection, loop chunks and loop edges; "graph": the pose graph;
#: "export": output files only.
STAGES = ("temporal", "loops", "graph", "export")

_KEY = "swiftjax.option"

T = TypeVar("T")

#: Largest magnitude any ``int`` option takes, whatever its own range (every integer the
#: pipeline passes on must fit a 32-bit index; ``10**23`` overflowed after the model load).
INT_LIMIT = 2**31 - 1


class OptionError(SwiftjaxError, ValueError):
    """An option value that the schema refuses; the message is one line naming the option."""


@dataclasses.dataclass(frozen=True)
class Spec:
    """The schema of one option (see the module docstring)."""

    kind: type
    help: str
    stage: str | None = None
    low: float | None = None
    high: float | None = None
    low_open: bool = False
    high_open: bool = False
    choices: tuple[str, ...] | None = None
    optional: bool = False
    finite: bool = True
    target: tuple[type, str] | None = None

    def allowed(self, name: str) -> str:
        """What the option accepts, in words: ``"an integer >= 2"``, ``"one of umeyama, irls"``."""
        if self.kind is bool:
            text = "true or false"
        elif self.choices is not None:
            text = "one of " + ", ".join(self.choices)
        else:
            text = {int: "an integer", float: "a finite number" if self.finite else "a number", str: "a string"}[
                self.kind
            ]
            if self.low is not None and self.high is not None:
                lo = "<" if self.low_open else "<="
                hi = "<" if self.high_open else "<="
                text += f" with {_num(self.low)} {lo} value {hi} {_num(self.high)}"
            elif self.low is not None:
                text += f" {'>' if self.low_open else '>='} {_num(self.low)}"
            elif self.high is not None:
                text += f" {'<' if self.high_open else '<='} {_num(self.high)}"
        if self.optional:
            text += " (or none)"
        return text


def _num(x: float) -> str:
    return str(int(x)) if float(x).is_integer() else repr(float(x))


#: ``option()``'s "not given" (a keyword left out keeps the target's schema, see :func:`option`).
_INHERIT: Any = type("_Inherit", (), {"__repr__": lambda self: "<inherited>"})()

#: The schema attributes of :class:`Spec` a field declaration gives (``stage`` and ``target`` aside).
_SCHEMA = ("kind", "help", "low", "high", "low_open", "high_open", "choices", "optional", "finite")


def option(
    default: Any = _INHERIT,
    help: Any = _INHERIT,
    *,
    stage: str | None = None,
    target: tuple[type, str] | None = None,
    kind: Any = _INHERIT,
    low: Any = _INHERIT,
    high: Any = _INHERIT,
    low_open: Any = _INHERIT,
    high_open: Any = _INHERIT,
    choices: Any = _INHERIT,
    optional: Any = _INHERIT,
    finite: Any = _INHERIT,
) -> Any:
    """A dataclass field with its schema: ``chunk_size: int = option(75, "frames per chunk (B)", low=2, stage="temporal")``.

    ``kind`` defaults to the type of ``default`` (give it when the default is ``None``).
    ``stage`` is one of :data:`STAGES`: the first stage whose stored result the option changes
    (given by :class:`~swiftjax.pipeline.PipelineConfig`'s fields; ``None`` for the fields of a
    stage option class).

    ``target=(StageClass, "field")``: the stage option this config field feeds (:func:`build`).
    The stage field is then the one declaration: its default, help, kind, range and choices
    are this field's too, and a keyword given here overrides one of them (a narrower range for
    the command line, the pipeline's own default):
    ``min_points: int = option(target=(AlignOptions, "min_points"), low=3, stage="temporal")``.
    A help text may name another field of its class as ``{name}``: :func:`specs` writes it as
    that field's name, or, for a config field, as the config field that feeds it.
    """
    given = {
        k: v
        for k, v in dict(
            help=help,
            kind=kind,
            low=low,
            high=high,
            low_open=low_open,
            high_open=high_open,
            choices=choices,
            optional=optional,
            finite=finite,
        ).items()
        if v is not _INHERIT
    }
    if target is not None:
        fields = {f.name: f for f in dataclasses.fields(target[0])}
        if target[1] not in fields or _NESTED in fields[target[1]].metadata:
            raise TypeError(f"option target {target[0].__name__}.{target[1]} is not a field")
        base = spec(fields[target[1]])
        values = {k: getattr(base, k) for k in _SCHEMA}
        if default is _INHERIT:
            default = fields[target[1]].default
    else:
        if default is _INHERIT or help is _INHERIT:
            raise TypeError("option() needs a default and a help text (or a target= to take them from)")
        values = {"kind": None, "low": None, "high": None, "low_open": False, "high_open": False}
        values.update(choices=None, optional=False, finite=True)
    values.update(given)
    if values["kind"] is None:
        if default is None:
            raise TypeError("option(None, ...) needs kind=")
        values["kind"] = type(default)
    if values["kind"] not in (bool, int, float, str):
        raise TypeError(f"option kind must be bool, int, float or str, got {values['kind']}")
    if stage is not None and stage not in STAGES:
        raise ValueError(f"option stage must be one of {STAGES}, got {stage!r}")
    if values["choices"] is not None:
        values["choices"] = tuple(values["choices"])
    s = Spec(stage=stage, target=target, **values)
    if default is not None or not s.optional:
        coerce(s, "default", default)  # a default outside its own schema is a programming error
    return dataclasses.field(default=default, metadata={_KEY: s})


def spec(field: dataclasses.Field[Any]) -> Spec:
    """The :class:`Spec` of a dataclass field declared with :func:`option`, as declared (its help
    may hold ``{field}`` references: :func:`specs` writes them out)."""
    try:
        return field.metadata[_KEY]
    except KeyError:
        raise TypeError(
            f"field {field.name!r} has no option schema: declare it with swiftjax.options.option(...)"
        ) from None


def specs(cls: Any) -> dict[str, Spec]:
    """``{field name: Spec}`` of every field of the dataclass ``cls`` declared with
    :func:`option` (every other field must be a :func:`nested` one), each help text's
    ``{name}`` references written out (:func:`option`)."""
    declared = {f.name: spec(f) for f in dataclasses.fields(cls) if _NESTED not in f.metadata}
    fed = {(s.target[0], s.target[1]): name for name, s in declared.items() if s.target is not None}

    def render(s: Spec) -> Spec:
        owner = s.target[0] if s.target is not None else None

        def name(m: re.Match[str]) -> str:
            return fed.get((owner, m.group(1)), m.group(1)) if owner is not None else m.group(1)

        return dataclasses.replace(s, help=_REFERENCE.sub(name, s.help)) if "{" in s.help else s

    return {name: render(s) for name, s in declared.items()}


#: A help text's reference to another field of its class: ``"fixed ({threshold})"``.
_REFERENCE = re.compile(r"\{(\w+)\}")


_NESTED = "swiftjax.option.nested"


def nested(cls: Any) -> Any:
    """A dataclass field holding a stage options object of class ``cls`` (default ``cls()``):
    ``verification_config: VerificationConfig = nested(VerificationConfig)``.  :func:`validate`
    checks its type; :func:`build` builds it from a config like a top-level one."""
    return dataclasses.field(default=cls(), metadata={_NESTED: cls})


def replace(instance: Any, **changes: Any) -> Any:
    """A validated copy of the options object ``instance`` with ``changes`` (every value,
    ``None`` included, is a value: ``None`` is only accepted by an optional field).

    Raises:
        OptionError: an unknown field (with the closest known one) or a refused value.
    """
    names = [f.name for f in dataclasses.fields(instance)]
    for key in changes:
        if key not in names:
            close = difflib.get_close_matches(key, names, n=1)
            hint = f" (did you mean {close[0]}?)" if close else ""
            raise OptionError(f"unknown option {key!r} of {type(instance).__name__}{hint}")
    return dataclasses.replace(instance, **changes)


def targets(config_cls: Any, cls: Any) -> dict[str, str]:
    """``{config field: stage field}`` of the fields of ``config_cls`` whose ``target`` is in ``cls``."""
    out = {}
    for f in dataclasses.fields(config_cls):
        s = f.metadata.get(_KEY)
        if s is not None and s.target is not None and s.target[0] is cls:
            out[f.name] = s.target[1]
    return out


def build(cls: Any, config: Any) -> Any:
    """The stage options ``cls`` of ``config`` (e.g. ``build(LoopOptions, pipeline_config)``):
    every field of ``config`` whose ``target`` is a field of ``cls`` gives that field its value,
    the :func:`nested` fields are built the same way, the rest keep ``cls``'s defaults."""
    values: dict[str, Any] = {stage: getattr(config, name) for name, stage in targets(type(config), cls).items()}
    for f in dataclasses.fields(cls):
        inner = f.metadata.get(_NESTED)
        if inner is not None and f.name not in values and targets(type(config), inner):
            values[f.name] = build(inner, config)
    return cls(**values)


class built(Generic[T]):
    """A read-only attribute of a config class: the stage options ``cls`` of the instance,
    :func:`build` at each access (``align = built(AlignOptions)`` gives ``config.align``)."""

    def __init__(self, cls: type[T]) -> None:
        self.cls = cls

    @overload
    def __get__(self, instance: None, owner: type) -> built[T]: ...
    @overload
    def __get__(self, instance: object, owner: type) -> T: ...
    def __get__(self, instance: object | None, owner: type) -> built[T] | T:
        return self if instance is None else build(self.cls, instance)


def stage_options(cls: Any, values: Mapping[str, Any], stage: str) -> dict[str, Any]:
    """The options of ``values`` that belong to ``stage`` (one of :data:`STAGES`)."""
    if stage not in STAGES:
        raise ValueError(f"stage must be one of {STAGES}, got {stage!r}")
    return {k: values[k] for k, s in specs(cls).items() if s.stage == stage}


def flag(name: str) -> str:
    """The command-line flag of an option: ``chunk_size -> --chunk-size``."""
    return "--" + name.replace("_", "-")


def invalid(where: str, value: Any, allowed: str, why: str = "") -> OptionError:
    """The one shape of an option error, naming the option first (``where``: ``Class.field``,
    a flag, or a key and its file): ``"AlignOptions.overlap_scale: invalid value 'x'; allowed:
    one of none, median, auto"``, or with ``why``: ``"LoopOptions.top_k: 0 is out of range;
    allowed: an integer >= 1"``."""
    shown = repr(value) if isinstance(value, str) else _show(value)
    said = f"{shown}{why}" if why else f"invalid value {shown}"
    return OptionError(f"{where}: {said}; allowed: {allowed}")


def coerce(s: Spec, name: str, value: Any, source: str | None = None) -> Any:
    """``value`` checked against ``s`` and normalised (ints to float for float options);
    :class:`OptionError` naming ``name`` (``Class.field``, a flag or a key; and ``source``, e.g.
    the TOML file) otherwise."""
    where = f"{name}" if source is None else f"{name} ({source})"
    given = value

    def fail(why: str = "") -> OptionError:
        return invalid(where, given, s.allowed(name), why)

    if value is None or (s.optional and isinstance(value, str) and value == "none"):
        if s.optional:
            return None
        raise fail()
    if s.kind is bool:
        if isinstance(value, bool):
            return value
        try:
            import numpy as np

            if isinstance(value, np.bool_):
                return bool(value)
        except ImportError:  # pragma: no cover
            pass
        raise fail(" is not a boolean")
    if s.kind is str:
        if not isinstance(value, str):
            raise fail(" is not a string")
        if s.choices is not None and value not in s.choices:
            raise fail()
        return value
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise fail(" is not a number")
    if s.kind is int:
        if not isinstance(value, numbers.Integral):
            raise fail(" is not an integer")
        value = int(value)
        if abs(value) > INT_LIMIT:  # no option means 10**23; past int64 it would overflow later
            raise fail(" is out of range")
    else:
        value = float(value)
        if s.finite and not math.isfinite(value):
            raise fail(" is not finite")
    if s.low is not None and (value < s.low or (s.low_open and value == s.low)):
        raise fail(" is out of range")
    if s.high is not None and (value > s.high or (s.high_open and value == s.high)):
        raise fail(" is out of range")
    return value


def _show(value: Any) -> str:
    if isinstance(value, numbers.Number) and type(value).__module__ == "numpy":
        value = value.item()  # 1000.0, not np.float64(1000.0)
    if isinstance(value, float) and math.isinf(value):
        return "inf (a number too large to represent?)" if value > 0 else "-inf"
    return repr(value)


def validate(instance: Any) -> None:
    """Check and normalise every field of a (frozen) dataclass instance in place (its
    ``__post_init__`` calls this); an error names ``Class.field``."""
    owner = type(instance).__name__
    for f in dataclasses.fields(instance):
        inner = f.metadata.get(_NESTED)
        if inner is not None:
            if not isinstance(getattr(instance, f.name), inner):
                raise invalid(f"{owner}.{f.name}", getattr(instance, f.name), f"a {inner.__name__}")
            continue
        value = coerce(spec(f), f"{owner}.{f.name}", getattr(instance, f.name))
        object.__setattr__(instance, f.name, value)


def _parse_cli(s: Spec, text: str) -> Any:
    """A command-line string as the option's type (validation happens in :func:`coerce`)."""
    if s.optional and text == "none":
        return None
    if s.kind is int:
        try:
            return int(text, 10)
        except ValueError:
            return text  # coerce names the option and says "not a number"/"not an integer"
    if s.kind is float:
        try:
            return float(text)
        except ValueError:
            return text
    return text


def from_sources(
    cls: Any,
    file_values: Mapping[str, Any] | None = None,
    cli_values: Mapping[str, Any] | None = None,
    *,
    file_name: str | None = None,
) -> Any:
    """Build ``cls`` from a config file's table (TOML values as parsed) and command-line values
    (strings, or booleans for flags; ``None`` = not given), the command line winning.

    Raises:
        OptionError: an unknown key (with the closest known one), or a value the schema refuses
            (naming the flag or the file's key).
    """
    table = specs(cls)
    values: dict[str, Any] = {}
    given: dict[str, str] = {}  # key -> "file" | "cli"
    for key, raw in (file_values or {}).items():
        if key not in table:
            close = difflib.get_close_matches(key, table, n=1)
            hint = f" (did you mean {close[0]}?)" if close else ""
            where = f" in {file_name}" if file_name else ""
            raise OptionError(f"unknown configuration key {key!r}{where}{hint}")
        values[key] = coerce(table[key], key, raw, source=file_name)
        given[key] = "file"
    for key, raw in (cli_values or {}).items():
        if raw is None:
            continue
        if key not in table:
            raise OptionError(f"unknown option {flag(key)}")
        parsed = _parse_cli(table[key], raw) if isinstance(raw, str) else raw
        values[key] = coerce(table[key], flag(key), parsed)
        given[key] = "cli"
    resolve = getattr(cls, "dependent_defaults", None)
    if resolve is not None:  # defaults that follow another option the user set (never a given value)
        values.update({k: v for k, v in resolve(values).items() if k not in values})
    try:
        return cls(**values)
    except OptionError as err:
        if cli_values is None:
            raise
        raise OptionError(speak(str(err), table, given, file_name)) from None


def speak(message: str, names: Iterable[str], given: Mapping[str, str], file_name: str | None = None) -> str:
    """A cross-option message in the command line's words: each option name written as its
    flag (``loop_half_window -> --loop-half-window``; ``NAME=false`` as ``--no-NAME``), except
    the keys the config file gave, and the subject's value marked as the default when the user
    never set it."""

    def subject(m: re.Match[str]) -> str:
        name, value = m.group(1), m.group(2)
        note = "" if name in given else " (the default: you did not set it)"
        return f"{name}: {value}{note};"

    message = re.sub(r"^\w+\.(?=\w+: )", "", message)  # "PipelineConfig.overlap: ..." -> "overlap: ..."
    message = re.sub(r"^(\w+): ([^;]*);", subject, message, count=1)
    for name in sorted(names, key=len, reverse=True):
        if given.get(name) == "file":
            continue
        message = re.sub(rf"(?<![\w-]){name}=false\b", "--no-" + flag(name)[2:], message)
        message = re.sub(rf"(?<![\w-]){name}=true\b", flag(name), message)
        message = re.sub(rf"(?<![\w-]){name}\b", flag(name), message)
    return message


def _metavar(name: str, s: Spec) -> str:
    if s.choices is not None:
        return "{" + ",".join(s.choices + (("none",) if s.optional else ())) + "}"
    return {int: "INT", float: "FLOAT", str: "TEXT"}[s.kind]


def add_arguments(parser: argparse.ArgumentParser | Any, cls: Any) -> None:
    """One flag per field of ``cls``: ``--x``/``--no-x`` for booleans, else a typed value.

    Flags default to ``None`` (= not given: the config file's value, else the field's default);
    the help shows the description, what is allowed and the default.  Values are checked by
    :func:`from_sources`, so a bad one is the same one-line error as in a config file.
    """
    table = specs(cls)
    for f in dataclasses.fields(cls):
        s = table[f.name]
        default = "none" if f.default is None else (str(f.default).lower() if s.kind is bool else f.default)
        if s.kind is bool:
            parser.add_argument(
                flag(f.name),
                dest=f.name,
                action=argparse.BooleanOptionalAction,
                default=None,
                help=f"{s.help} (default: {default})",
            )
        else:
            parser.add_argument(
                flag(f.name),
                dest=f.name,
                default=None,
                metavar=_metavar(f.name, s),
                help=f"{s.help}; {s.allowed(f.name)} (default: {default})",
            )
