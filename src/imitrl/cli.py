"""Command line: ``imitrl frozenlake [--out DIR] [--protocol batched] [--<field> VALUE ...]``.

Every field of :class:`~imitrl.experiments.frozenlake.StudyConfig` is a flag (dashes
for underscores); its help text is the field's docstring. Tuples are comma-separated
(``--sweep-sizes 1,3,10``; chain panels as ``eps:T`` pairs, ``--chain-panels 0.05:10,0.01:64``),
booleans take ``--flag`` / ``--no-flag``, optional values take ``none``.
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import inspect
import itertools
import logging
import sys
import types
import typing
from collections.abc import Sequence
from pathlib import Path

import torch

from imitrl.experiments.frozenlake import StudyConfig, run_study

__all__ = ["main"]


def _field_docs(cls: type) -> dict[str, str]:
    """The docstring written under each dataclass field (the ``field: type`` then ``\"\"\"doc\"\"\"`` idiom)."""
    tree = ast.parse(inspect.getsource(cls))
    body = tree.body[0].body
    docs = {}
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
        return lambda s: None if s.lower() == "none" else inner(s)
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

            return pairs
        return lambda s: tuple(item(x) for x in s.split(",") if x)
    if tp is Path:
        return Path
    return tp


def _add_config_flags(parser: argparse.ArgumentParser, cls: type) -> None:
    docs = _field_docs(cls)
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        flag = "--" + f.name.replace("_", "-")
        default = f.default
        help_text = f"{docs.get(f.name, '')} (default: {default})"
        if hints[f.name] in (bool, bool | None):
            parser.add_argument(
                flag,
                dest=f.name,
                action=argparse.BooleanOptionalAction,
                default=default,
                help=help_text,
            )
        else:
            parser.add_argument(
                flag,
                dest=f.name,
                type=_parser_for(hints[f.name]),
                default=default,
                help=help_text,
                metavar=f.name.upper(),
            )


def build_parser() -> argparse.ArgumentParser:
    """The ``imitrl`` argument parser (one subcommand per study)."""
    parser = argparse.ArgumentParser(
        prog="imitrl", description="imitrl: imitation learning on TorchRL"
    )
    sub = parser.add_subparsers(dest="command", required=True)
    lake = sub.add_parser(
        "frozenlake",
        help="reproduce the FrozenLake study (expert, BC, compounding error, DAgger, exercises)",
        description="Every experiment of the FrozenLake section on imitrl's pipeline, with the exact value "
        "beside every Monte Carlo estimate. Writes report.txt, results.json and figures to --out.",
    )
    _add_config_flags(lake, StudyConfig)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the ``imitrl`` command; returns the exit status (2 on bad input)."""
    args = build_parser().parse_args(argv)
    if args.command == "frozenlake":
        torch.set_num_threads(1)  # the simulators are bandwidth-bound; threads only contend
        logging.getLogger("torchrl").setLevel(logging.WARNING)
        values = {f.name: getattr(args, f.name) for f in dataclasses.fields(StudyConfig)}
        try:
            run_study(StudyConfig(**values))
        except ValueError as err:  # bad flags, unknown env ids, maps without a tabular model
            print(f"imitrl frozenlake: {err}", file=sys.stderr)
            return 2
        return 0
    return 2  # pragma: no cover - argparse enforces a command


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
