"""Keep the per-node copies in ``swpc.dbc`` identical to the node-1 definitions.

The protocol is written once, as the ``Sync`` message and the ``N1_*`` messages of node 1.
Every controller node uses the same layouts at ``id = node << 5 | command``; so that plain
``cantools decode swpc.dbc`` decodes a log of any node, the DBC also lists the copies
``N2_*`` .. ``N8_*``.  This tool regenerates those copies from the node-1 block::

    python -m firmware_protocol.dbc_nodes          # rewrite swpc.dbc in place
    python -m firmware_protocol.dbc_nodes --check  # exit 1 if the file is out of date

Edit only ``Sync`` and ``N1_*``; the test suite fails if the copies drift.
"""

from __future__ import annotations

import argparse
import copy
import sys
from pathlib import Path

import cantools
from cantools.database.can import Database, Message, Node

DBC_PATH = Path(__file__).with_name("swpc.dbc")
MAX_NODE = 8
"""Highest controller node id the DBC describes (the id layout allows up to 63)."""
NODE_SHIFT = 5
COMMAND_MASK = (1 << NODE_SHIFT) - 1


def _copy_for_node(msg: Message, node: int) -> Message:
    """Return ``msg`` (a node-1 message) re-addressed to ``node``: id, name, sender, receivers."""
    new = copy.deepcopy(msg)
    new.frame_id = (node << NODE_SHIFT) | (msg.frame_id & COMMAND_MASK)
    new.name = f"N{node}_" + msg.name.removeprefix("N1_")
    new.senders[:] = [f"Ctrl{node}" if s == "Ctrl1" else s for s in msg.senders]
    for sig in new.signals:
        sig.receivers[:] = [f"Ctrl{node}" if r == "Ctrl1" else r for r in sig.receivers]
    return new


def expand(db: Database, max_node: int = MAX_NODE) -> Database:
    """Database with ``Sync``, ``N1_*`` and generated copies for nodes 2..``max_node``.

    Broadcast messages (node 0, e.g. ``Sync``) list every controller as receiver.
    """
    base = [m for m in db.messages if (m.frame_id >> NODE_SHIFT) in (0, 1)]
    out = copy.deepcopy(db)
    out.messages.clear()
    ctrls = [f"Ctrl{k}" for k in range(1, max_node + 1)]
    for msg in base:
        if msg.frame_id >> NODE_SHIFT == 0:
            bc = copy.deepcopy(msg)
            for sig in bc.signals:
                sig.receivers[:] = [r for r in sig.receivers if not r.startswith("Ctrl")] + ctrls
            out.messages.append(bc)
    for node in range(1, max_node + 1):
        for msg in base:
            if msg.frame_id >> NODE_SHIFT == 1:
                out.messages.append(_copy_for_node(msg, node) if node > 1 else msg)
    out.nodes.clear()
    out.nodes.append(Node("Host", comment=None))
    out.nodes.extend(Node(name, comment=None) for name in ctrls)
    out.refresh()
    return out


def render(path: Path = DBC_PATH) -> str:
    """The expanded DBC text for the DBC at ``path``."""
    db = cantools.database.load_file(str(path), strict=True, sort_signals=None)
    assert isinstance(db, Database)
    return expand(db).as_dbc_string(sort_signals=None).replace("\r\n", "\n")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true", help="only check, do not write")
    parser.add_argument("path", nargs="?", type=Path, default=DBC_PATH)
    args = parser.parse_args(argv)
    text = render(args.path)
    current = args.path.read_text()
    if args.check:
        if text != current:
            print(f"{args.path} is out of date: run python -m firmware_protocol.dbc_nodes")
            return 1
        return 0
    args.path.write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
