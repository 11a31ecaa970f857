"""The robot config a commissioning found, as a correction of the one in force.

:func:`corrected_config` edits the robot config document *as written* (the file's YAML,
or nothing for the embedded default): only the keys a fix needs change, every other key
and its value stay as the operator wrote them.  What each finding
(:class:`swpc_hw.calibration.commission.analysis.Finding`) becomes:

* ``crossed`` (module ``m``'s drives move module ``p``): ``drives.modules[p]`` takes what
  the config gave ``m`` (each kind's nodes and settings per module);
* ``swapped``: not in the config, on any kind: the module's motors' connectors.  Each
  drive is set up for the motor it drives (its tuning and current limits, a CiA 402
  drive's gear ratio 0x6091, the steering's homing input and method), so exchanging the
  nodes in the config would leave each motor on the other's settings; ``swpc`` has one
  node for both;
* ``polarity``: ``polarity[p][axis]`` turns sign (swpc applies it to what a run commands
  and reads; docs/commissioning.md says how each kind can hold it instead);
* ``ratio``: the axis' ``gear_ratio`` times the ratio found (``odrive``); a CiA 402
  drive's own gear ratio (0x6091) must change with the config's, and ``swpc``'s firmware
  holds its own: the config alone cannot;
* ``zero``: the module's nominal ``beta`` (the config's ``nominal``) at the zero found;
* the motion-capture body turned, the sensor not seeing the robot, what is not known: the
  config has no place for them.

All the fixes of one commissioning are for the physical modules: a module's axes are
corrected where its drives land once crossed nodes are put right.
"""

from __future__ import annotations

import copy
import difflib
from typing import Any

import yaml

from services.config.robot import RobotConfig
from swpc_hw.calibration.commission.analysis import Commissioning

RATIO_IN_CONFIG = ("odrive",)
"""The drive kinds whose ratio the config alone holds (a CiA 402 drive keeps its own gear
ratio, 0x6091, which swpc checks against the config's: both change together)."""


def _key(d: dict[Any, Any], module: int) -> Any:
    """``module``'s key in a mapping read from YAML or JSON (an int or its text)."""
    return module if module in d or str(module) not in d else str(module)


def corrected_config(
    config: RobotConfig, text: str | None, c: Commissioning
) -> tuple[dict[str, Any], str, list[str]]:
    """``(document, diff, not in the config)``: the robot config document ``text`` (YAML;
    None: the embedded default, an empty document) with every fix of ``c`` the config can
    hold (module docstring), the unified difference between the two as YAML, and the
    findings it cannot hold (their texts)."""
    old = yaml.safe_load(text) if text else {}
    if not isinstance(old, dict):
        old = {}
    doc = copy.deepcopy(old)
    kind = config.drives.kind
    effective = config.to_document()
    modules = effective["drives"]["modules"]  # module (text) -> its nodes, as the config says
    rest: list[str] = []

    def drives_modules() -> dict[Any, Any]:
        d = doc.setdefault("drives", {"kind": kind})
        if "modules" not in d or d["modules"] is None:
            d["modules"] = {int(m): copy.deepcopy(v) for m, v in modules.items()}
        return dict(d["modules"])

    crossed = {f.module: int(f.value) for f in c.findings if f.what == "crossed"}
    if crossed:
        current = drives_modules()
        new = dict(current)
        for p, m in crossed.items():
            assert p is not None
            new[_key(current, p)] = copy.deepcopy(current[_key(current, m)])
        doc["drives"]["modules"] = new
    for f in c.findings:
        p = f.module
        if f.what == "polarity" and p is not None:
            # relative to the polarity the probes ran with: that of the module whose
            # drives move p
            was = effective["polarity"].get(str(crossed.get(p, p))) or {}
            pol = doc.setdefault("polarity", {})
            k = _key(pol, p)
            axes = dict(pol.get(k) or {})
            axes[f.axis] = -int(was.get(f.axis, 1))
            pol[k] = axes
        elif f.what == "ratio" and p is not None:
            if kind in RATIO_IN_CONFIG:
                mods = drives_modules()
                axis = mods[_key(mods, p)][f.axis]
                axis["gear_ratio"] = round(float(axis.get("gear_ratio", 1.0)) * f.value, 6)
                doc["drives"]["modules"] = mods
            else:
                rest.append(f.text)
        elif f.what == "zero" and p is not None:
            nominal = doc.get("nominal")
            if not isinstance(nominal, dict) or "modules" not in nominal:
                nominal = copy.deepcopy(effective["nominal"])
                doc["nominal"] = nominal
            for mod in nominal["modules"]:
                if int(mod["id"]) == p:
                    mod["beta"] = round(f.value, 6)
        elif f.what != "crossed":
            rest.append(f.text)
    if doc.get("polarity"):  # polarity 1 on both axes is the default: left out
        doc["polarity"] = {
            m: {a: v for a, v in axes.items() if v != 1}
            for m, axes in doc["polarity"].items()
            if any(v != 1 for v in axes.values())
        } or None
        if doc["polarity"] is None:
            del doc["polarity"]
    diff = "".join(
        difflib.unified_diff(
            _yaml(old).splitlines(keepends=True),
            _yaml(doc).splitlines(keepends=True),
            "robot.yaml (in force)",
            "robot.yaml (commissioned)",
        )
    )
    return doc, diff, rest


def with_int_keys(doc: dict[str, Any]) -> dict[str, Any]:
    """A config document back from JSON (every key text): the module ids of
    ``drives.modules`` and ``polarity`` ints again, as YAML writes them."""
    out = copy.deepcopy(doc)
    drives = out.get("drives")
    if isinstance(drives, dict) and isinstance(drives.get("modules"), dict):
        drives["modules"] = {int(k): v for k, v in drives["modules"].items()}
    if isinstance(out.get("polarity"), dict):
        out["polarity"] = {int(k): v for k, v in out["polarity"].items()}
    return out


def _yaml(doc: dict[str, Any]) -> str:
    return yaml.safe_dump(doc, sort_keys=False, default_flow_style=False) if doc else ""
