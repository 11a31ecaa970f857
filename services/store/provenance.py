"""Where a kinematic file came from: tool version and commit, hashes of its inputs.

The version is the installed package's (``swpc --version``); the commit is read from the
checkout the package runs from (``/opt/swpc`` on a robot: ``.git/HEAD`` and its ref, no
``git`` process), ``None`` when it is not a git checkout.  Hashes are SHA-256: of a
dataset, the files that define it (``robot.yaml``, ``poses.csv``, ``encoders.csv``,
``segments.csv``, each hashed and then hashed together with its name); of a robot config,
its canonical JSON (sorted keys).
"""

from __future__ import annotations

import functools
import hashlib
import json
from importlib import metadata
from pathlib import Path
from typing import Any

DATASET_FILES = ("robot.yaml", "poses.csv", "encoders.csv", "segments.csv")
UNITS = {"length": "m", "angle": "rad", "time": "s"}


@functools.cache
def tool_version() -> str:
    try:
        return metadata.version("swpc")
    except metadata.PackageNotFoundError:
        return "unknown"


@functools.cache
def git_commit() -> str | None:
    """The commit of the checkout this package runs from (``None`` if not a checkout)."""
    root = Path(__file__).resolve().parents[1]
    git = root / ".git"
    try:
        if git.is_file():  # a worktree: "gitdir: <path>"
            git = Path(git.read_text(encoding="utf-8").split(":", 1)[1].strip())
        head = (git / "HEAD").read_text(encoding="utf-8").strip()
        if not head.startswith("ref:"):
            return head or None
        ref = head.split(":", 1)[1].strip()
        common = git
        if (git / "commondir").is_file():
            common = (git / (git / "commondir").read_text(encoding="utf-8").strip()).resolve()
        for base in (git, common):
            if (base / ref).is_file():
                return (base / ref).read_text(encoding="utf-8").strip()
        for base in (git, common):
            packed = base / "packed-refs"
            if packed.is_file():
                for line in packed.read_text(encoding="utf-8").splitlines():
                    if line.endswith(" " + ref):
                        return line.split(" ", 1)[0]
    except (OSError, IndexError, UnicodeDecodeError):
        return None
    return None


def version_line() -> str:
    commit = git_commit()
    return f"swpc {tool_version()}" + (f" (commit {commit[:12]})" if commit else "")


def file_sha256(path: Path) -> str:
    h = hashlib.sha256()
    with path.open("rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def dataset_sha256(directory: str | Path) -> str:
    """SHA-256 over the dataset's defining files (module docstring)."""
    d = Path(directory)
    h = hashlib.sha256()
    for name in DATASET_FILES:
        p = d / name
        if p.is_file():
            h.update(f"{name}\0{file_sha256(p)}\n".encode())
    return h.hexdigest()


def config_sha256(doc: Any) -> str:
    """SHA-256 of a document's canonical JSON (sorted keys, no spaces)."""
    text = json.dumps(doc, sort_keys=True, separators=(",", ":"), allow_nan=True)
    return hashlib.sha256(text.encode()).hexdigest()


def provenance(tool: str, **fields: Any) -> dict[str, Any]:
    """The ``provenance`` mapping of a kinematic file: tool, version, commit, then
    ``fields`` (``None`` values left out)."""
    out: dict[str, Any] = {"tool": tool, "version": tool_version(), "commit": git_commit()}
    out.update({k: v for k, v in fields.items() if v is not None})
    return out
