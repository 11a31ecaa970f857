"""The ``swpc`` command: one subcommand per module of this package.

Every module here whose name does not start with ``_`` is a subcommand (discovered at
start-up, as cantools discovers its subparsers): it defines ``register(subparsers) ->
None``, which adds its parser and sets ``func(args) -> int`` as default.  Heavy imports
stay inside ``func`` so that ``swpc --help`` is fast.  Add a subcommand by adding a
module.

Errors the user can act on (bad input, a file, a CAN interface that cannot be opened)
are one line on stderr, ``swpc <command>: error: ...``, and exit status 2; a bug keeps
its traceback.
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import pkgutil
import sys
from collections.abc import Sequence

from firmware_protocol.errors import FirmwareProtocolError
from swpc_hw.errors import SwpcError

SERVICE_EXTRA_PROBES = ("scipy", "can", "fastapi", "zenoh", "threadpoolctl")
"""One import name per part of pyproject's ``service`` extra that every command needs."""


def missing_service_extra() -> str | None:
    """The first of :data:`SERVICE_EXTRA_PROBES` not installed (a robot that installed
    ``swpc`` for its odometry only), or None."""
    return next((m for m in SERVICE_EXTRA_PROBES if importlib.util.find_spec(m) is None), None)


def subcommand_modules() -> list[str]:
    """Dotted names of the subcommand modules, sorted."""
    return sorted(
        f"{__name__}.{info.name}"
        for info in pkgutil.iter_modules(__path__)
        if not info.name.startswith("_")
    )


def build_parser() -> argparse.ArgumentParser:
    from services.store.provenance import version_line

    parser = argparse.ArgumentParser(
        prog="swpc", description="Calibration system for single-wheel powered caster robots."
    )
    parser.add_argument("--version", action="version", version=version_line())
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in subcommand_modules():
        importlib.import_module(name).register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    missing = missing_service_extra()
    if missing is not None:
        print(
            f"swpc: error: no module {missing!r}: the swpc command needs the extra 'service' "
            "(pip install 'swpc[service]'); a robot that runs only the odometry does not",
            file=sys.stderr,
        )
        return 2
    from swpc_hw.blas_threads import single_blas_thread

    single_blas_thread()
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args))
    except (SwpcError, FirmwareProtocolError, OSError) as exc:
        print(f"swpc {args.command}: error: {one_line(exc)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
    except Exception as exc:
        if type(exc).__module__.split(".")[0] != "can":  # a bug: keep its traceback
            raise
        print(f"swpc {args.command}: error: CAN: {one_line(exc)}", file=sys.stderr)
        return 2


def one_line(exc: BaseException) -> str:
    """The error's message on one line (an OSError with its errno name and file)."""
    if isinstance(exc, OSError) and exc.strerror:
        where = f"{exc.filename}: " if exc.filename else ""
        return f"{where}{exc.strerror}"
    text = " ".join(str(exc).split())
    return text or type(exc).__name__


if __name__ == "__main__":
    sys.exit(main())
