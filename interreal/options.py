"""One way from command-line options to a stage's configuration: a dataclass field declared with `option(...)`
carries its flag, help and choices, `add_flags` makes the argparse flags from the fields, and `values_from_args`
reads them back, so an option is added in one place (the field).

Flags default to None (not given): the field's default then applies, and a preset or caller value is not
overridden by a flag the user did not type. A bool field becomes a switch: `--NAME` sets True, or with a flag
spelled `--no-...`, False.
"""

from __future__ import annotations

import argparse
from dataclasses import MISSING, Field, field, fields
from typing import Any, TypeVar

from .errors import InputError

T = TypeVar("T")


def option(default: Any, help: str, *, flag: str | None = None, choices: tuple | None = None,
           metavar: str | None = None, exclusive: str | None = None, nargs: str | None = None) -> Any:
    """A dataclass field that is also a command-line flag (`--field-name` unless `flag`); `help` says why.
    Fields with the same `exclusive` name are mutually exclusive flags; `nargs` ("*", "+") makes a tuple field a
    list of values."""
    return field(default=default, metadata={"help": help, "flag": flag, "choices": choices, "metavar": metavar,
                                            "exclusive": exclusive, "nargs": nargs})


def config_from(cls: type[T], opts: dict[str, Any], what: str) -> T:
    """`cls` from a stage's keyword options (None = the field's default); InputError naming unknown `what` options."""
    unknown = set(opts) - {f.name for f in fields(cls)}
    if unknown:
        raise InputError(f"unknown {what} options {sorted(unknown)}")
    return cls(**{k: v for k, v in opts.items() if v is not None})


def options_of(cls: type, opts: dict[str, Any]) -> dict[str, Any]:
    """The entries of `opts` that are fields of `cls` (a command that runs several stages splits its options)."""
    names = {f.name for f in fields(cls)}
    return {k: v for k, v in opts.items() if k in names}


def flag_fields(cls: type) -> list[Field]:
    """The fields of a dataclass declared with `option`, in declaration order."""
    return [f for f in fields(cls) if "help" in f.metadata]


def flag_name(f: Field) -> str:
    return f.metadata.get("flag") or "--" + f.name.replace("_", "-")


def add_flags(parser: argparse.ArgumentParser | argparse._ArgumentGroup, cls: type,
              skip: tuple[str, ...] = ()) -> None:
    """One flag per `option` field of `cls` (dest = the field name, default None = not given); `skip`: field
    names left out (a command that sets them itself)."""
    groups: dict[str, Any] = {}
    for f in flag_fields(cls):
        if f.name in skip:
            continue
        name, meta = flag_name(f), f.metadata
        default = f.default if f.default is not MISSING else None
        where = parser
        if meta.get("exclusive"):
            if meta["exclusive"] not in groups:
                groups[meta["exclusive"]] = parser.add_mutually_exclusive_group()
            where = groups[meta["exclusive"]]
        if isinstance(default, bool):
            where.add_argument(name, dest=f.name, action="store_const", const=not name.startswith("--no-"),
                               default=None, help=meta["help"])
            continue
        kind = _scalar_type(f, default)
        shown = "auto" if default is None else "none" if default == () else default
        extra = {"nargs": meta["nargs"]} if meta.get("nargs") else {}
        where.add_argument(name, dest=f.name, type=kind, default=None, choices=meta.get("choices"),
                           metavar=meta.get("metavar"), help=f"{meta['help']} (default {shown})".replace("%", "%%"),
                           **extra)


def values_from_args(cls: type, args: argparse.Namespace) -> dict[str, Any]:
    """{field: value} of every `option` field of `cls`: the flag's value when given, else the field's default."""
    return {f.name: f.default for f in flag_fields(cls)} | given_values(cls, args)


def given_values(cls: type, args: argparse.Namespace) -> dict[str, Any]:
    """{field: value} of the `option` fields of `cls` whose flags were given (to lay over a preset)."""
    return {f.name: getattr(args, f.name) for f in flag_fields(cls) if getattr(args, f.name, None) is not None}


def _scalar_type(f: Field, default: Any) -> type:
    annotation = str(f.type)
    annotation = annotation.removeprefix("tuple[")  # a list flag (nargs): the type of each value
    for name, kind in (("int", int), ("float", float), ("str", str)):
        if annotation == name or annotation.startswith((f"{name} ", f"{name}|", f"{name},")):
            return kind
    return type(default) if default is not None else str
