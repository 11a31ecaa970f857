"""The CAN frame table in ``docs/can-protocol.md`` is the one the DBC gives."""

from __future__ import annotations

from pathlib import Path

import pytest

from firmware_protocol import codec, frame_table

ROOT = Path(__file__).resolve().parents[1]
CAN_DOC = ROOT / "docs" / "can-protocol.md"


# ---------------------------------------------------------------------------- frame table
def test_can_doc_frame_table_is_the_one_the_dbc_gives() -> None:
    doc = CAN_DOC.read_text(encoding="utf-8")
    assert frame_table.current_block(doc) == frame_table.block(), (
        "docs/can-protocol.md's frame table differs from firmware_protocol/swpc.dbc: run "
        "python -m firmware_protocol.frame_table --write docs/can-protocol.md"
    )


def test_frame_table_lists_every_command_with_its_dbc_layout() -> None:
    db = frame_table.load()
    text = frame_table.markdown(db)
    for cmd in codec.Command:
        name = "Sync" if cmd == codec.Command.SYNC else codec.COMMAND_NAMES[cmd]
        assert f"### 0x{int(cmd):02X} {name}\n" in text, name
        msg = db.get_message_by_frame_id(int(cmd) if cmd == codec.Command.SYNC else 1 << 5 | cmd)
        for sig in msg.signals:
            row = f"| {sig.name} | {sig.start}"
            assert row in text.split(f"### 0x{int(cmd):02X} ")[1].split("###")[0], row
    assert "| SteerPosition | 0..19 | i20 | 2π/2¹⁷ ≈ 4.7937e-05 |" in text
    assert "| Homed | 48 | u1 |" in text
    assert "host → all controllers" in text and "controller n → host" in text


def test_frame_table_follows_a_change_of_the_dbc() -> None:
    db = frame_table.load()
    before = frame_table.block(db)
    db.get_message_by_name("N1_Heartbeat").cycle_time = 50
    db.get_message_by_name("N1_SetLimits").get_signal_by_name("MaxTorque").scale = 0.002
    after = frame_table.block(db)
    heartbeat = "| [Heartbeat](#0x06-heartbeat) | controller n → host | 8 | 50 ms |"
    assert heartbeat in after and heartbeat.replace("50 ms", "100 ms") in before
    assert "| MaxTorque | 8..23 | u16 | 0.002 |" in after and before != after
    doc = CAN_DOC.read_text(encoding="utf-8")
    assert frame_table.current_block(doc) != after  # the doc check would fail on it


def test_frame_table_update_rewrites_only_its_block(tmp_path: Path) -> None:
    doc = tmp_path / "doc.md"
    doc.write_text(f"intro\n\n{frame_table.BEGIN}\nstale\n{frame_table.END}\n\noutro\n")
    assert frame_table.update(doc) is True
    text = doc.read_text()
    assert text.startswith("intro\n\n") and text.endswith("\n\noutro\n")
    assert frame_table.current_block(text) == frame_table.block()
    assert frame_table.update(doc) is False
    doc.write_text("no markers\n")
    with pytest.raises(ValueError, match="no generated frame table"):
        frame_table.update(doc)
