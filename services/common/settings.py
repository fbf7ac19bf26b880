"""Settings declared once. A core's parameters are a frozen dataclass whose fields are made with
`setting(default, help=..., bounds or choices)`; the pydantic config model of the service that
runs the core (its TOML table, environment variables and validation) is derived from that
declaration (`config_fields`), and so are command-line flags (`add_flag`), so a setting's name,
type, default, help and allowed values are written in one place. The cores import only this
module's `setting`, which needs nothing but the standard library.

Command lines: every parser is a `CommandParser` (whole flag names only), and a flag that was
renamed keeps its old spelling as `add_renamed_flag`, read as before and noted.
"""

from __future__ import annotations

import argparse
import dataclasses
import types
import typing
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Literal

from services.common.errors import ConfigError

_BOUNDS = ("ge", "gt", "le", "lt")


REQUIRED = ...   # setting(REQUIRED, ...): a setting with no default, that must be given


def setting(default: Any, *, help: str, choices: tuple[str, ...] | None = None, ge: float | None = None,
            gt: float | None = None, le: float | None = None, lt: float | None = None) -> Any:
    """A dataclass field with its documentation and its allowed values (``default`` REQUIRED:
    none, the setting must be given; such fields come first in their dataclass). A default of
    None means "not set", allowed beside the choices and bounds."""
    metadata = {"help": help, "choices": choices, "ge": ge, "gt": gt, "le": le, "lt": lt}
    if default is REQUIRED:
        return dataclasses.field(metadata=metadata)
    return dataclasses.field(default=default, metadata=metadata)


def declared(params_type: type) -> list[tuple[dataclasses.Field, Any]]:
    """(field, resolved type) of every field of a parameters dataclass."""
    hints = typing.get_type_hints(params_type)
    return [(f, hints[f.name]) for f in dataclasses.fields(params_type)]


_COMPARE = {"ge": lambda v, b: v >= b, "gt": lambda v, b: v > b, "le": lambda v, b: v <= b, "lt": lambda v, b: v < b}


def check(params) -> None:
    """Raise ConfigError naming the first field of ``params`` outside its declared bounds or
    choices (``LABEL`` of the dataclass, if any, leads the message). None (an optional setting
    left unset) is within any bounds."""
    kind = getattr(type(params), "LABEL", type(params).__name__)
    for f, _ in declared(type(params)):
        value, meta = getattr(params, f.name), f.metadata
        choices = meta.get("choices")
        if value is None and f.default is None:
            continue
        if choices:
            if value not in choices:
                raise ConfigError(f"{kind}: invalid {f.name} = {value!r} (choose one of {', '.join(choices)})")
            continue
        broken = [bound for bound in _BOUNDS if meta.get(bound) is not None and value is not None
                  and not _COMPARE[bound](value, meta[bound])]
        if broken:
            raise ConfigError(f"{kind}: invalid {f.name} = {value!r} (must be {_SAY[broken[0]]} {meta[broken[0]]})")


_SAY = {"ge": ">=", "gt": ">", "le": "<=", "lt": "<"}


def config_fields(params_type: type, prefix: str = "", *, optional: bool = False) -> dict[str, tuple[Any, Any]]:
    """pydantic.create_model field definitions for every setting of ``params_type``, named
    ``prefix + name``, with its default, description and bounds. ``optional``: each field may be
    None and is None by default, meaning "the service's own setting" (a model that passes
    settings on to a service, such as the whole run's, leaves the default to the service)."""
    from pydantic import Field

    fields = {}
    for f, annotation in declared(params_type):
        meta = f.metadata
        if meta.get("choices"):
            annotation = Literal[meta["choices"]] | None if f.default is None else Literal[meta["choices"]]
        bounds = {bound: meta[bound] for bound in _BOUNDS if meta.get(bound) is not None}
        description = meta.get("help", "")
        if optional:
            annotation, default = annotation | None, None
            description = f"{description} (default: the service's, {f.default})"
        else:
            default = ... if f.default is dataclasses.MISSING else f.default
        fields[prefix + f.name] = (annotation, Field(default, description=description, **bounds))
    return fields


def passed_on(model, *names: str, rename: Mapping[str, str] | None = None) -> dict[str, tuple[Any, Any]]:
    """pydantic.create_model field definitions for settings that a model (such as the whole run's)
    passes on to the service whose config ``model`` declares them: each field's type, bounds and
    description as declared there, but optional and None by default, "the service's own setting"
    (as config_fields(optional=True) for a core's dataclass). ``rename``: {name: key} where the
    passing model's key differs."""
    from pydantic import Field

    fields = {}
    for name in names:
        field = model.model_fields[name]
        inner = _not_none(field.annotation)
        annotation = (typing.Annotated[(inner, *field.metadata)] if field.metadata else inner) | None
        default = field.get_default(call_default_factory=True)
        said = "" if default in (None, False, [], {}) else f" (default: the service's, {_shown(default)})"
        description = (field.description or "").rstrip(".") + said
        fields[(rename or {}).get(name, name)] = (annotation, Field(None, description=description))
    return fields


def params_of(params_type: type, values, prefix: str = ""):
    """The ``params_type`` whose fields a config model (or mapping) holds under ``prefix``."""
    get = values.get if isinstance(values, dict) else lambda name: getattr(values, name)
    return params_type(**{f.name: get(prefix + f.name) for f in dataclasses.fields(params_type)})


def _not_none(annotation: Any) -> Any:
    """X of an X | None annotation (else the annotation)."""
    if typing.get_origin(annotation) in (typing.Union, types.UnionType):
        return next(arg for arg in typing.get_args(annotation) if arg is not type(None))
    return annotation


def add_flag(parser, params_type: type, name: str, *, prefix: str = "", flag: str | tuple[str, ...] | None = None,
             shown_default: Any = None, standalone: bool = False, **extra) -> None:
    """An argparse flag for one declared setting (default None: "not given"), its type, choices
    and help from the declaration. ``flag``: its spelling (or spellings, e.g. ("-l", "--listen");
    default --NAME). A bool setting is a switch: --no-NAME sets it false, any other spelling
    true. ``shown_default``: the default --help names when the command's differs from the
    declaration's (None: the declaration's; a default of None or a switch's is not shown, the
    help says what happens). ``standalone``: a command's own flag that no config model reads
    after it: its default is the declared one and the declared bounds are checked as it is
    parsed (a flag read into a config model is checked there, naming the flag)."""
    f, annotation = next((f, a) for f, a in declared(params_type) if f.name == name)
    meta = f.metadata
    annotation = _not_none(annotation)
    flags = (flag,) if isinstance(flag, str) else tuple(flag or ("--" + (prefix + name).replace("_", "-"),))
    default = shown_default if shown_default is not None else f.default
    text = meta.get("help", "").rstrip(".").replace("%", "%%")   # argparse formats help with %
    kwargs: dict[str, Any] = {"dest": prefix + name}
    if annotation is bool:
        off = flags[-1].startswith("--no-")
        kwargs.update(action="store_false" if off else "store_true", default=None)
        kwargs["help"] = f"{text} (on by default; {flags[-1]} turns it off)" if off else text   # a switch: off unless given
    else:
        shown = default not in (None, "") and default is not dataclasses.MISSING
        kwargs["help"] = f"{text} (default {_shown(default)})" if shown else text
        if meta.get("choices"):
            kwargs["choices"] = list(meta["choices"])
        elif annotation in (int, float, Path):
            kwargs["type"] = _bounded(annotation, meta) if standalone else annotation
    if standalone:
        kwargs["default"] = f.default if f.default is not dataclasses.MISSING else None
    parser.add_argument(*flags, **{**kwargs, **extra})


def _shown(value: Any) -> str:
    return ",".join(str(item) for item in value) if isinstance(value, (list, tuple)) else str(value)


def _bounded(kind: type, meta) -> Any:
    """argparse's type for a number within the declared bounds."""
    def convert(text: str):
        value = kind(text)   # a ValueError: argparse's "invalid int value"
        for bound in _BOUNDS:
            if meta.get(bound) is not None and not _COMPARE[bound](value, meta[bound]):
                raise argparse.ArgumentTypeError(f"expected a number {_SAY[bound]} {meta[bound]:g}, got {text!r}")
        return value

    convert.__name__ = kind.__name__
    return convert


def add_field_flag(parser, model, name: str, *, flag: str | tuple[str, ...] | None = None, **extra) -> None:
    """An argparse flag for one field of a pydantic config model (default None: "not given"):
    its type, choices, help and default from the field; a bool field is a switch that sets it
    true. ``flag``: its spelling or spellings (default --NAME). For the settings a service
    declares in its config model rather than a core's dataclass."""
    field = model.model_fields[name]
    annotation = _not_none(field.annotation)
    default = field.get_default(call_default_factory=True)
    if isinstance(default, (list, tuple)):
        default = ", ".join(str(item) for item in default) or None
    # None or empty: the description says what happens; a switch is off unless given
    said = "" if default in (None, {}) or (annotation is bool and default is False) else f" (default {default})"
    text = (field.description or "").rstrip(".").replace("%", "%%")   # argparse formats help with %
    kwargs: dict[str, Any] = {"dest": name, "help": f"{text}{said}"}
    if annotation is bool:
        kwargs.update(action="store_true", default=None)
    elif typing.get_origin(annotation) is Literal:
        kwargs["choices"] = list(typing.get_args(annotation))
    elif annotation in (int, float, Path):
        kwargs["type"] = annotation
    flags = (flag,) if isinstance(flag, str) else tuple(flag or ("--" + name.replace("_", "-"),))
    parser.add_argument(*flags, **{**kwargs, **extra})


class CommandParser(argparse.ArgumentParser):
    """An argparse parser that reads only whole flag names: with abbreviations a flag left out or
    mistyped is silently read as another (`--map DIR` as `--map-optimizer DIR`). Its
    sub-commands' parsers are CommandParsers too."""

    def __init__(self, *args, allow_abbrev: bool = False, **kwargs):
        super().__init__(*args, allow_abbrev=allow_abbrev, **kwargs)


RENAMED = "renamed_flags"   # the parsed arguments' list of old flag spellings used: [(old, new)]


def note_renamed(namespace: argparse.Namespace, old: str, new: str) -> None:
    """Record that the command line used `old`, the former spelling of `new`."""
    if getattr(namespace, RENAMED, None) is None:
        setattr(namespace, RENAMED, [])
    getattr(namespace, RENAMED).append((old, new))


class _Renamed(argparse.Action):
    def __init__(self, option_strings, dest, new: str, **kwargs):
        self.new = new
        super().__init__(option_strings, dest, **kwargs)

    def __call__(self, parser, namespace, values, option_string=None):
        setattr(namespace, self.dest, values)
        note_renamed(namespace, option_string, self.new)


def add_renamed_flag(parser, old: str, new: str, **kwargs) -> None:
    """`old`, the former spelling of the flag `new`: still read, into the same destination, left
    out of --help, and noted (`renamed_flags`) so that the command line can say so."""
    parser.add_argument(old, action=_Renamed, new=new, help=argparse.SUPPRESS, default=argparse.SUPPRESS, **kwargs)


def renamed_flags(args: argparse.Namespace) -> list[str]:
    """One line for each old flag spelling the command line used."""
    return [f"{old} is now spelled {new}; the old spelling still works but will go"
            for old, new in dict.fromkeys(getattr(args, RENAMED, None) or [])]
