"""The ``swpc`` command: one subcommand per module.

Each subcommand module defines ``register(subparsers) -> None``, which adds its parser
and sets ``func(args) -> int`` as default.  Heavy imports stay inside ``func`` so that
``swpc --help`` is fast.  Add a subcommand by listing its module in ``SUBCOMMANDS``.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

from swpc_hw.errors import SwpcError

SUBCOMMANDS: tuple[str, ...] = (
    "swpc_hw.commands.solve",
    "simulators.commands_gen",
    "services.commands_serve",
    "swpc_hw.commands.can",
    "simulators.commands_sim",
    "swpc_hw.commands.validate",
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="swpc", description="Calibration system for single-wheel powered caster robots."
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in SUBCOMMANDS:
        module = importlib.import_module(name)
        module.register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args))
    except SwpcError as exc:
        print(f"swpc {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
