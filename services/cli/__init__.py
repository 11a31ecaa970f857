"""The ``swpc`` command: one subcommand per module of this package.

Every module here whose name does not start with ``_`` is a subcommand (discovered at
start-up, as cantools discovers its subparsers): it defines ``register(subparsers) ->
None``, which adds its parser and sets ``func(args) -> int`` as default.  Heavy imports
stay inside ``func`` so that ``swpc --help`` is fast.  Add a subcommand by adding a
module.
"""

from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys
from collections.abc import Sequence

from firmware_protocol.errors import FirmwareProtocolError
from swpc_hw.errors import SwpcError


def subcommand_modules() -> list[str]:
    """Dotted names of the subcommand modules, sorted."""
    return sorted(
        f"{__name__}.{info.name}"
        for info in pkgutil.iter_modules(__path__)
        if not info.name.startswith("_")
    )


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="swpc", description="Calibration system for single-wheel powered caster robots."
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in subcommand_modules():
        importlib.import_module(name).register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args))
    except (SwpcError, FirmwareProtocolError) as exc:
        print(f"swpc {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
