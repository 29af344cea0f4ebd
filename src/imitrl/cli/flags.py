"""Flags from a frozen config dataclass: every field is a flag, its docstring the help.

A field ``num_envs: int = 1`` becomes ``--num-envs NUM_ENVS`` (dashes for
underscores) with the field's docstring and default as help text. Types:

* ``bool`` (or ``bool | None``): ``--flag`` / ``--no-flag``;
* ``X | None``: the word ``none`` gives None;
* ``tuple[X, ...]``: comma-separated (``--hidden 64,64``); ``tuple[tuple[A, B], ...]``:
  comma-separated ``a:b`` pairs (``--chain-panels 0.05:10,0.01:64``);
* ``Path``, ``int``, ``float``, ``str``: converted by the type itself.

Two field metadata switches serve commands that wrap another program
(``imitrl bench NAME [args...]``): ``{"positional": True}`` makes the field a
positional argument, ``{"remainder": True}`` collects every argument after the
positionals (``tuple[str, ...]``). ``{"flag": "--name"}`` names the flag otherwise than
the field (``BCConfig.num_steps`` is ``--steps``: :func:`imitrl.limits.flag_of`);
``{"aliases": ("--other-name",)}`` adds flag names
(one name for one idea across commands: ``--max-episode-steps`` everywhere).
``{"repeat": "--env-kwarg"}`` makes a ``tuple[tuple[str, object], ...]`` field a
repeatable flag of ``name=value`` pairs (``--env-kwarg obs_type=pixels_agent_pos
--env-kwarg terminate_on_success=False``): the value is a Python literal where it reads
as one (``False``, ``3``, ``0.5``, ``(84, 84)``), else the string.

Defaults are shown in the help as they are typed: ``64,64``, ``0.05:10``, ``none``; a
field declared with :func:`imitrl.limits.bounded` shows its range after the default
(``(default: 5); must be an integer in [0, 10_000]``), from the one record its config's
validation reads.

A value the type cannot read (``--steps 2.5``, ``--hidden 64,x``) is an argparse error:
one line on stderr naming the flag, exit status 2 (:class:`OneLineParser`).
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import inspect
import itertools
import types
import typing
from pathlib import Path

from imitrl.limits import flag_of

__all__ = ["OneLineParser", "add_config_flags", "config_from_args", "field_docs"]


class OneLineParser(argparse.ArgumentParser):
    """An argument parser whose errors are one line on stderr (``imitrl bc: argument
    --steps: invalid int value: '2.5'``) and exit status 2, as every other bad input of
    the command line; ``--help`` still shows the usage."""

    def error(self, message: str) -> typing.NoReturn:
        self.exit(2, f"{self.prog}: {' '.join(message.split())}\n")


def field_docs(cls: type) -> dict[str, str]:
    """The docstring written under each dataclass field (``field: type`` then ``\"\"\"doc\"\"\"``).

    Base classes are read too, so a config that extends another documents the
    inherited fields with their own docstrings.
    """
    docs: dict[str, str] = {}
    for klass in reversed(cls.__mro__):
        if not dataclasses.is_dataclass(klass):
            continue
        tree = ast.parse(inspect.getsource(klass))
        definition = tree.body[0]
        assert isinstance(definition, ast.ClassDef)  # the source of a class: its definition
        body = definition.body
        for node, nxt in itertools.pairwise(body):
            if isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
                if (
                    isinstance(nxt, ast.Expr)
                    and isinstance(nxt.value, ast.Constant)
                    and isinstance(nxt.value.value, str)
                ):
                    docs[node.target.id] = " ".join(nxt.value.value.split())
    return docs


def _parser_for(tp) -> typing.Callable[[str], object]:
    """A string -> value converter for a (possibly optional or tuple) field type."""
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin in (typing.Union, types.UnionType) and type(None) in args:
        inner = _parser_for(next(a for a in args if a is not type(None)))

        def optional(text: str) -> object:
            return None if text.lower() == "none" else inner(text)

        optional.__name__ = f"{getattr(inner, '__name__', 'value')} or none"
        return optional
    if origin is tuple:
        item = args[0]
        if typing.get_origin(item) is tuple:  # pairs "a:b"
            a, b = typing.get_args(item)

            def pairs(text: str) -> tuple:
                out = []
                for part in filter(None, text.split(",")):
                    left, sep, right = part.partition(":")
                    if not sep:
                        raise argparse.ArgumentTypeError(
                            f"expected comma-separated a:b pairs, got {part!r}"
                        )
                    out.append((a(left), b(right)))
                return tuple(out)

            pairs.__name__ = f"comma-separated a:b pairs of {a.__name__}:{b.__name__}"
            return pairs

        def items(text: str) -> tuple:
            parts = text.split(",") if text else []
            if item is str:  # an empty string is a value (its field says if it may be one)
                return tuple(parts)
            if "" in parts:  # "64,,64" or "64,": a value left out, never read as (64, 64)
                raise argparse.ArgumentTypeError(f"an empty value between commas in {text!r}")
            return tuple(item(x) for x in parts)

        items.__name__ = f"comma-separated {item.__name__}"  # argparse's "invalid ... value"
        return items
    if tp is Path:
        return Path
    return tp


_WORDS = {"true": True, "false": False, "none": None, "null": None}
"""the values shells, JSON and YAML spell in lower case (``is_slippery=false`` was the
string ``'false'``, which is true, and the lake stayed slippery)"""


def _name_value(text: str) -> tuple[str, object]:
    """``"name=value"`` -> ``(name, value)``, the value a Python literal where it is one
    (``true``, ``false``, ``none``, ``null`` too); a string otherwise (quote a string that
    reads as one of those: ``name='false'``)."""
    name, sep, value = text.partition("=")
    if not sep or not name.isidentifier():
        raise argparse.ArgumentTypeError(f"expected name=value with a keyword name, got {text!r}")
    if value in _WORDS:
        return name, _WORDS[value]
    try:
        return name, ast.literal_eval(value)
    except (ValueError, SyntaxError):
        return name, value


def shown(value: object) -> str:
    """A default as it is typed on the command line (``(64, 64)`` -> ``64,64``)."""
    if value is None:
        return "none"
    if isinstance(value, tuple):
        return ",".join(":".join(map(str, v)) if isinstance(v, tuple) else str(v) for v in value)
    return str(value)


def add_config_flags(parser: argparse.ArgumentParser, cls: type) -> None:
    """Add one flag (or positional) per field of the dataclass ``cls`` to ``parser``."""
    docs = field_docs(cls)
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        doc = docs.get(f.name, "")
        if f.metadata.get("positional"):
            parser.add_argument(
                f.name, type=_parser_for(hints[f.name]), metavar=f.name.upper(), help=doc
            )
            continue
        if f.metadata.get("remainder"):
            parser.add_argument(f.name, nargs=argparse.REMAINDER, metavar=f.name.upper(), help=doc)
            continue
        if f.metadata.get("repeat"):
            parser.add_argument(
                f.metadata["repeat"],
                dest=f.name,
                type=_name_value,
                action="append",
                default=[],
                help=f"{doc} (repeat the flag for several)",
                metavar="NAME=VALUE",
            )
            continue
        flags = [flag_of(f), *f.metadata.get("aliases", ())]
        default = f.default
        required = default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING
        bound = f.metadata.get("bound")  # imitrl.limits.bounded: the range it checks
        ranged = "" if bound is None else f"; must be {bound.help(default)}"
        given = "required" if required else f"default: {shown(default)}"
        help_text = f"{doc} ({given}){ranged}".replace("%", "%%")  # argparse
        if hints[f.name] in (bool, bool | None):
            parser.add_argument(
                *flags,
                dest=f.name,
                action=argparse.BooleanOptionalAction,
                default=default,
                help=help_text,
            )
        else:
            parser.add_argument(
                *flags,
                dest=f.name,
                type=_parser_for(hints[f.name]),
                required=required,  # a field without a default: argparse says it is missing
                default=None if required else default,
                help=help_text,
                metavar=f.name.upper(),
            )


def config_from_args(cls: type, args: argparse.Namespace):
    """The ``cls`` instance the parsed flags describe (its ``__post_init__`` validates it)."""
    values = {f.name: getattr(args, f.name) for f in dataclasses.fields(cls)}
    for f in dataclasses.fields(cls):
        if f.metadata.get("remainder") or f.metadata.get("repeat"):
            values[f.name] = tuple(values[f.name])
    return cls(**values)
