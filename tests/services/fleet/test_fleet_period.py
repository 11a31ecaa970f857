"""The fleet's word for how often a robot publishes its state is the fleet period
(``fleet_period_s``, format ``swpc-fleet-state/2``), never the drives' heartbeat; documents
of format /1 (``heartbeat_s``) are still read."""

from __future__ import annotations

import json

import pytest

from services.config.fleet import STATE_FORMAT, STATE_FORMAT_1
from services.fleet.service import DocumentError, check_document
from services.fleet.view import summary

BASE = {"robot": "a", "history": {"calibrations": []}, "file_in_force": None,
        "last_check": None}  # fmt: skip


def doc(**fields: object) -> dict[str, object]:
    return {**BASE, **fields}


def test_a_document_states_its_fleet_period() -> None:
    d = check_document("a", json.dumps(doc(format=STATE_FORMAT, fleet_period_s=5)).encode())
    row = summary("a", d, 0, [], 1, first_seen=0.0, last_seen=100.0, alive=None, now=116.0,
                  stale_periods=3)  # fmt: skip
    assert row["fleet_period_s"] == 5 and "heartbeat_s" not in row
    assert row["status"] == "stale" and "3 fleet periods of 5 s" in row["stale_reason"]


def test_a_format_1_document_is_read_by_its_heartbeat_s() -> None:
    d = check_document("a", json.dumps(doc(format=STATE_FORMAT_1, heartbeat_s=5)).encode())
    row = summary("a", d, 0, [], 1, first_seen=0.0, last_seen=100.0, alive=None, now=110.0,
                  stale_periods=3)  # fmt: skip
    assert row["fleet_period_s"] == 5 and row["status"] == "live"


def test_the_new_format_needs_the_new_name() -> None:
    with pytest.raises(DocumentError, match="fleet_period_s None"):
        check_document("a", json.dumps(doc(format=STATE_FORMAT, heartbeat_s=5)).encode())
