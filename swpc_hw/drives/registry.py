"""The drive kinds by name: the robot config's ``drives:`` -> a kind -> its :class:`Drives`.

A *kind* (:class:`Kind`) is a name, the model of its part of the robot config (a
:class:`KindConfig`: its ``kind`` and where each module's axes are) and an opener (the
kind's config, the bus and timing settings, the clock -> its UNCONFIGURED
:class:`~swpc_hw.drives.interface.Drives`).  Nothing else in swpc asks which kind a robot
has.

Where a kind is found (as python-can finds its interfaces: a built-in table, then the
``can.interface`` entry points), by name, the first place that has it:

1. :data:`BUILTIN`: the three kinds swpc ships (``swpc``, ``cia402``, ``odrive``), each a
   :class:`Kind` named ``KIND`` in its package, imported when first asked for;
2. :func:`register` (a kind defined in a running program, e.g. a test's);
3. the entry points of group :data:`ENTRY_POINT_GROUP` of any installed distribution,
   the entry point's name the kind's, its object a :class:`Kind`::

       # the pyproject.toml of a package that adds a kind
       [project.entry-points."swpc.drives"]
       mykind = "mypackage.drives:KIND"

An unknown name is a :class:`~swpc_hw.drives.errors.CanConfigError` naming the known
ones.  docs/drives.md (*The library: drives as an API*) shows a kind written from scratch.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass
from importlib.metadata import entry_points
from typing import Annotated, Any

from pydantic import BaseModel, BeforeValidator, ConfigDict, SerializeAsAny

from swpc_hw.clock import SYSTEM_CLOCK, Clock
from swpc_hw.drives.bus import CanConfig
from swpc_hw.drives.errors import CanConfigError
from swpc_hw.drives.interface import Drives

STRICT = ConfigDict(extra="forbid", allow_inf_nan=False, frozen=True)

DEFAULT_KIND = "swpc"

ENTRY_POINT_GROUP = "swpc.drives"
"""The entry-point group other packages add drive kinds to (module docstring)."""

BUILTIN = {
    "swpc": "swpc_hw.drives.swpc:KIND",
    "cia402": "swpc_hw.drives.cia402:KIND",
    "odrive": "swpc_hw.drives.odrive:KIND",
}
"""The kinds swpc ships: name -> ``module:attribute`` of its :class:`Kind`."""


class KindConfig(BaseModel):
    """What every kind's model has: its ``kind`` and the module ids it maps."""

    model_config = STRICT

    kind: str

    def module_ids(self) -> list[int] | None:
        """The module ids the config maps (None: not given, numbered by default)."""
        raise NotImplementedError

    def check_modules(self, ids: list[int]) -> list[str]:
        """Why this config does not fit a robot with module ids ``ids`` (empty when it
        does)."""
        mine = self.module_ids()
        if mine is not None and sorted(mine) != sorted(ids):
            return [f"drives.modules must map exactly the module ids {ids}, not {sorted(mine)}"]
        return []

    def for_modules(self, ids: list[int]) -> KindConfig:
        """This config with its default module map filled in for ``ids``."""
        return self

    def nodes(self) -> list[int]:
        """Every CAN node id the drives use (for a listing; each kind numbers its own)."""
        raise NotImplementedError

    def axis_nodes(self) -> dict[int, tuple[int, int]]:
        """Module id -> the nodes of its steering and its wheel drive (one node twice for a
        module whose two axes share a controller); the default numbering must have been
        filled in (:meth:`for_modules`)."""
        raise NotImplementedError


Opener = Callable[[Any, CanConfig, Clock], Drives]


@dataclass(frozen=True)
class Kind:
    """A drive kind: its name, its config's model, its opener (module docstring)."""

    name: str
    config: type[KindConfig]
    open: Opener


_registered: dict[str, Kind] = {}


def register(kind: Kind) -> None:
    """Make ``kind`` known by its name (a built-in name cannot be taken)."""
    if kind.name in BUILTIN:
        raise CanConfigError(f"drives.kind: {kind.name!r} is a built-in kind")
    _registered[kind.name] = kind


def unregister(name: str) -> None:
    """Forget a kind :func:`register` made known (no-op for another)."""
    _registered.pop(name, None)


def _entry_points() -> dict[str, Any]:
    return {ep.name: ep for ep in entry_points(group=ENTRY_POINT_GROUP)}


def known() -> list[str]:
    """Every kind's name, sorted."""
    return sorted(set(BUILTIN) | set(_registered) | set(_entry_points()))


def _loaded(name: str, obj: Any) -> Kind:
    if not isinstance(obj, Kind) or obj.name != name:
        raise CanConfigError(f"drives.kind {name!r}: {obj!r} is not a Kind named {name!r}")
    return obj


def get(name: str) -> Kind:
    """The kind called ``name`` (module docstring); :class:`CanConfigError` naming the
    known kinds for an unknown one."""
    if name in BUILTIN:
        module, attr = BUILTIN[name].split(":")
        return _loaded(name, getattr(importlib.import_module(module), attr))
    if name in _registered:
        return _registered[name]
    ep = _entry_points().get(name)
    if ep is None:
        raise CanConfigError(
            f"drives.kind: unknown kind {name!r} (known: {', '.join(known())})"
        )
    return _loaded(name, ep.load())


def parse_drives(value: Any) -> Any:
    """A ``drives:`` value as its kind's config: the short form ``drives: <kind>`` is
    ``{kind: <kind>}``, a mapping is validated by the model of the kind it names (default
    :data:`DEFAULT_KIND`); a config already made is kept."""
    if isinstance(value, str):
        value = {"kind": value}
    if isinstance(value, KindConfig):
        return value
    if isinstance(value, dict):
        name = value.get("kind", DEFAULT_KIND)
        if not isinstance(name, str):
            raise ValueError(f"drives.kind: a name, not {name!r}")
        try:
            kind = get(name)
        except CanConfigError as exc:
            raise ValueError(str(exc)) from None
        return kind.config.model_validate(value)
    return value


DrivesConfig = Annotated[SerializeAsAny[KindConfig], BeforeValidator(parse_drives)]
"""A robot config's ``drives:``: the config of the kind it names (:func:`parse_drives`)."""


def open_drives(
    config: KindConfig, bus: CanConfig, module_ids: list[int], *, clock: Clock = SYSTEM_CLOCK
) -> Drives:
    """The drives of ``config`` for a robot with ``module_ids``, UNCONFIGURED (call
    ``configure()``); :class:`CanConfigError` for a config that does not fit the robot or
    a kind that is not known."""
    problems = config.check_modules(module_ids)
    if problems:
        raise CanConfigError("; ".join(problems))
    return get(config.kind).open(config.for_modules(module_ids), bus, clock)
