"""Typed configuration dataclasses and the command-line options generated from them (nerfstudio-style).

Each command's options are the fields of one dataclass: the field name gives the flag (`--max-bounces`),
the type its parser, the default its default, and the `help` metadata its help text. A field declared with
`option(..., positional=True)` may also be given as an optional positional argument (`neumatex render ASSET`).
"""

from __future__ import annotations

import argparse
import dataclasses
import shlex
import types
import typing
from typing import Any, TypeVar

C = TypeVar("C")
POSITIONAL_SUFFIX = "_positional"


def option(default: Any, help: str, **kw: Any) -> Any:  # noqa: A002 - mirrors argparse's name
    """A dataclass field carrying its command-line help text."""
    if isinstance(default, list | tuple | dict):
        return dataclasses.field(default_factory=lambda: type(default)(default), metadata={"help": help, **kw})
    return dataclasses.field(default=default, metadata={"help": help, **kw})


def add_config_arguments(parser: argparse.ArgumentParser, cls: type) -> None:
    """Add one `--flag` per field of the dataclass `cls`."""
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        flag = "--" + f.name.replace("_", "-")
        typ = hints[f.name]
        args = typing.get_args(typ)
        if isinstance(typ, types.UnionType) or typing.get_origin(typ) is typing.Union:
            typ = next(a for a in args if a is not type(None))
            args = typing.get_args(typ)
        if f.default is not dataclasses.MISSING:
            default = f.default
        elif f.default_factory is not dataclasses.MISSING:
            default = f.default_factory()
        else:
            default = None
        text = str(f.metadata.get("help", "")).replace("%", "%%")  # argparse %-formats help strings
        helptext = f"{text} (default: {str(default).replace('%', '%%')})"
        if f.metadata.get("positional"):
            parser.add_argument(f.name + POSITIONAL_SUFFIX, nargs="?", default=None, metavar=f.name.upper(),
                                help=f"{text} (same as {flag})")
        if typ is bool:
            parser.add_argument(flag, action=argparse.BooleanOptionalAction, default=default, help=helptext)
        elif typing.get_origin(typ) is tuple:
            parser.add_argument(
                flag,
                type=args[0],
                nargs=len(args),
                default=default,
                help=helptext,
                metavar=tuple(f"{f.name[0].upper()}{i}" for i in range(len(args))),
            )
        elif typing.get_origin(typ) is typing.Literal:
            parser.add_argument(flag, choices=list(args), default=default, help=helptext)
        else:
            parser.add_argument(flag, type=typ, default=default, help=helptext)


def config_from_args(cls: type[C], ns: argparse.Namespace) -> C:
    """Build the dataclass `cls` from parsed arguments."""
    values = {}
    for f in dataclasses.fields(cls):  # type: ignore[arg-type]
        value = getattr(ns, f.name)
        given = getattr(ns, f.name + POSITIONAL_SUFFIX, None) if f.metadata.get("positional") else None
        if given is not None:
            if value != f.default and value != given:
                raise ValueError(f"{f.name.upper()} given twice ({given!r} and --{f.name.replace('_', '-')} {value!r})")
            value = given
        values[f.name] = tuple(value) if isinstance(value, list) else value
    return cls(**values)


def command_line(program: str, config: Any, skip: tuple[str, ...] = ()) -> str:
    """The shell command that rebuilds `config` (a config dataclass instance) through `add_config_arguments`:
    positional fields first, then every other field that differs from its default, except those in `skip`."""
    words, flags = [program], []
    for f in dataclasses.fields(config):
        value = getattr(config, f.name)
        if f.name in skip:
            continue
        if f.metadata.get("positional"):
            words.append(shlex.quote(str(value)))
        elif value != f.default:
            flag = "--" + f.name.replace("_", "-")
            if isinstance(value, bool):
                flags.append(flag if value else "--no-" + flag[2:])
            else:
                values = value if isinstance(value, tuple) else (value,)
                flags.append(" ".join([flag, *(shlex.quote(str(v)) for v in values)]))
    return " ".join(words + flags)


@dataclasses.dataclass(frozen=True)
class Range:
    """The allowed values of a numeric config field: lo <= x <= hi (lo < x when lo_open). Written once beside the
    config (e.g. `TTOConfig` -> `tto.config.RANGES`); `check_ranges` applies it and the job service turns it into
    the bounds of its request model (services/jobconfig.py)."""

    lo: float
    hi: float
    lo_open: bool = False

    def __contains__(self, x: object) -> bool:
        if not isinstance(x, int | float) or isinstance(x, bool):
            return False
        return (self.lo < x if self.lo_open else self.lo <= x) and x <= self.hi

    def describe(self) -> str:
        return f"{'>' if self.lo_open else '>='} {self.lo:g} and <= {self.hi:g}"


def check_ranges(config: Any, ranges: dict[str, Range], what: str) -> None:
    """ValueError naming the first field of `config` outside its Range (`what`: the config's name in messages)."""
    for name, allowed in ranges.items():
        value = getattr(config, name)
        if value not in allowed:
            raise ValueError(f"{what} {name} must be {allowed.describe()}, got {value!r}")


def literal_choices(cls: type) -> dict[str, tuple[Any, ...]]:
    """The allowed values of every Literal-typed field of the dataclass `cls`."""
    hints = typing.get_type_hints(cls)
    return {f.name: typing.get_args(hints[f.name]) for f in dataclasses.fields(cls)
            if typing.get_origin(hints[f.name]) is typing.Literal}  # fmt: skip


def check_choices(config: Any, what: str) -> None:
    """ValueError naming the first Literal-typed field of the dataclass instance `config` holding another value."""
    for name, allowed in literal_choices(type(config)).items():
        if getattr(config, name) not in allowed:
            raise ValueError(f"{what} {name} must be one of {allowed}, got {getattr(config, name)!r}")


def check_known_keys(cls: type, data: dict[str, Any], what: str) -> None:
    """ValueError listing the keys of `data` that are not fields of the dataclass `cls` (`what`: its name in the
    message, e.g. "TTO config"), so a stored or posted config with a typo is refused rather than half-applied."""
    unknown = sorted(set(data) - {f.name for f in dataclasses.fields(cls)})
    if unknown:
        raise ValueError(f"unknown {what} keys {unknown}")


def parse_shard(text: str) -> tuple[int, int]:
    """(I, K) of a --shard option "I/K" (this process takes the items at positions i with i mod K == I), checked."""
    try:
        i, k = (int(x) for x in text.split("/"))
    except ValueError:
        raise ValueError(f"--shard: expected I/K such as 0/4, got {text!r}") from None
    if k < 1 or not 0 <= i < k:
        raise ValueError(f"--shard: need 0 <= I < K, got {text!r}")
    return i, k
