"""The repository explains itself: its docs exist, link only inside it, and the CAN frame
table in ``docs/can-protocol.md`` is the one the DBC gives.

Fast (no I/O beyond reading the Markdown files and the DBC once).
"""

from __future__ import annotations

import re
from pathlib import Path
from urllib.parse import unquote

import pytest

from firmware_protocol import codec, frame_table
from tests.service_rig import ROOT

DOCS = ROOT / "docs"
CAN_DOC = DOCS / "can-protocol.md"
DOC_FILES = ("README.md", "model-and-frames.md", "dataset-format.md", "kinematic-file.md",
             "can-protocol.md", "console.md")


def checked_files() -> list[Path]:
    """The Markdown files whose links must stay inside the repository."""
    files = [ROOT / "README.md", ROOT / "deploy" / "README.md",
             ROOT / "firmware_protocol" / "README.md"]
    return files + sorted(DOCS.rglob("*.md"))


# ---------------------------------------------------------------------------- link check
FENCE = re.compile(r"^\s*(```|~~~)")
INLINE_CODE = re.compile(r"(`+)(?:(?!\1).)+?\1")
HTML_COMMENT = re.compile(r"<!--.*?-->", re.S)
INLINE_LINK = re.compile(r"\]\(\s*<?([^)\s>]*)>?(?:\s+(?:\"[^\"]*\"|'[^']*'))?\s*\)")
REFERENCE_DEF = re.compile(r"^ {0,3}\[[^\]\n]+\]:[ \t]*<?([^\s>]+)>?", re.M)
HTML_ATTR = re.compile(r"\b(?:href|src)\s*=\s*[\"']([^\"']*)[\"']", re.I)
AUTOLINK = re.compile(r"<([a-zA-Z][a-zA-Z0-9+.-]*:[^>\s]*)>")
BARE_URL = re.compile(r"\b(?:https?|ftp)://\S+|\bwww\.[a-z0-9-]+\.\S+", re.I)
SCHEME = re.compile(r"^[a-zA-Z][a-zA-Z0-9+.-]*:")


def prose(text: str) -> str:
    """``text`` without code (fenced blocks, inline spans) and HTML comments: what renders
    as prose, where a link is a link."""
    out, fenced = [], False
    for line in HTML_COMMENT.sub("", text).splitlines():
        if FENCE.match(line):
            fenced = not fenced
            continue
        if not fenced and not line.startswith("    "):
            out.append(INLINE_CODE.sub("", line))
    return "\n".join(out)


def link_targets(text: str) -> list[str]:
    """Every link target of a Markdown text (inline, reference, HTML, autolinks, bare URLs)."""
    body = prose(text)
    found = []
    for rx in (INLINE_LINK, REFERENCE_DEF, HTML_ATTR, AUTOLINK):
        found += [m.group(1) for m in rx.finditer(body)]
        body = rx.sub(" ", body)
    # what is left: URLs in the prose, which GitHub renders as links too
    return found + [m.group(0).rstrip(".,;:!?)'\"") for m in BARE_URL.finditer(body)]


def bad_links(path: Path, root: Path = ROOT) -> list[str]:
    """Links of the Markdown file ``path`` that leave ``root`` or point at nothing."""
    bad = []
    for target in link_targets(path.read_text(encoding="utf-8")):
        where = f"{path.relative_to(root)}: {target!r}"
        if SCHEME.match(target) or target.startswith(("//", "www.")):
            bad.append(f"{where}: leaves the repository")
            continue
        rel = unquote(target.split("#", 1)[0].split("?", 1)[0])
        if not rel:
            continue  # an anchor in the same file
        if rel.startswith("/"):
            bad.append(f"{where}: absolute path (use a path relative to the file)")
            continue
        dest = (path.parent / rel).resolve()
        if not dest.is_relative_to(root.resolve()):
            bad.append(f"{where}: resolves outside the repository")
        elif not dest.exists():
            bad.append(f"{where}: no such file")
    return bad


def test_docs_exist_and_the_index_lists_each() -> None:
    index = (DOCS / "README.md").read_text(encoding="utf-8")
    for name in DOC_FILES:
        assert (DOCS / name).is_file(), name
    for doc in DOCS.glob("*.md"):
        if doc.name != "README.md":
            assert f"]({doc.name})" in index, f"docs/README.md does not link {doc.name}"
    assert list((DOCS / "history").glob("*.md")), "docs/history/ has no dated record"


@pytest.mark.parametrize("path", checked_files(), ids=lambda p: str(p.relative_to(ROOT)))
def test_links_stay_inside_the_repository_and_resolve(path: Path) -> None:
    assert bad_links(path) == []
    assert "../shared" not in path.read_text(encoding="utf-8")


def test_link_check_catches_what_it_must(tmp_path: Path) -> None:
    root = tmp_path / "repo"
    (root / "docs").mkdir(parents=True)
    (root / "docs" / "there.md").write_text("# there\n")
    doc = root / "docs" / "doc.md"
    doc.write_text(
        "Good: [a](there.md), [b](there.md#there), [c](#local), [d](../docs/),\n"
        "[`e`](there.md \"title\"), ![f](there.md).\n"
        "Code is not a link: `http://127.0.0.1:8080/health`, `[x](../../out.md)`\n"
        "```sh\ncurl https://example.com/x\n```\n"
        "    indented code: https://example.com/y\n"
        "<!-- a comment: [g](missing.md) -->\n"
        "Bad: [h](https://example.com/h), [i](../../outside.md), [j](missing.md),\n"
        "[k](/abs/path.md), <https://example.com/k>, see http://example.com/l,\n"
        '<a href="http://example.com/m">m</a>, [n](mailto:someone@example.com).\n'
        "[ref]: ../../../ref.md\n"
    )
    bad = bad_links(doc, root)
    assert [b.split(": ", 2)[1] for b in bad] == [
        "'https://example.com/h'",
        "'../../outside.md'",
        "'missing.md'",
        "'/abs/path.md'",
        "'mailto:someone@example.com'",
        "'../../../ref.md'",
        "'http://example.com/m'",
        "'https://example.com/k'",
        "'http://example.com/l'",
    ]
    assert "resolves outside the repository" in bad[1] and "no such file" in bad[2]


def test_readme_starts_with_the_two_set_up_commands() -> None:
    lines = (ROOT / "README.md").read_text(encoding="utf-8").splitlines()
    assert lines[1:6] == ["", "```sh", "make demo", "make test", "```"]


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
