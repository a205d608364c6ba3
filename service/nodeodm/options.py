"""The node's options: geomatch's own option table (geomatch.options) as NodeODM lists options, so
that an option added there is offered by REST, gRPC and the node alike.

NodeODM names options with dashes (``snap-radius``) and gives each exactly five keys (WebODM builds
``NodeOption(**o)`` from them and fails on any other): ``name``, ``type`` (int, float, string,
bool or enum), ``value`` (the default, as a string), ``domain`` (the values an enum takes, else a
few words on the range) and ``help``. A task's options come back as ``[{name, value}]`` with
values as JSON or as strings (WebODM sends its form's text): names the node does not know are
dropped, as NodeODM drops them (WebODM sends its presets, written for ODM, to every node); a known
name with a value its option refuses is an error.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Any

from geomatch.options import OPTIONS, PROJECT_OPTIONS, Option, OptionError
from geomatch_core.errors import InvalidRequest

# the reconstruct job's option the node takes besides a project's: GCPs held out as check points
CHECKPOINTS = "checkpoints"
CHECKPOINTS_HELP = (
    "ground control points held out of the fit to judge it: how many (spread over the points' "
    "names) or their names, comma separated (with a GCP file among the task's files)"
)
NODE_OPTIONS = (*PROJECT_OPTIONS, CHECKPOINTS)
# where the node's default is not the table's: a WebODM task's map is the first thing WebODM shows
# (ODM always makes one), so a task makes it unless told ``ortho: off``
NODE_DEFAULTS: dict[str, Any] = {"ortho": "on"}


def node_name(name: str) -> str:
    return name.replace("_", "-")


def _domain(o: Option) -> str | list[str]:
    if o.choices:
        return list(o.choices)
    if o.type in (int, float):
        kind = "integer" if o.type is int else "float"
        if o.low is None and o.high is None:
            return kind
        zero = f"0 ({o.zero}) or " if o.zero else ""
        return f"{kind}: {zero}{o.low:g} to {o.high:g}{o.unit}"
    return "string"


def _type(o: Option) -> str:
    if o.choices:
        return "enum"
    return {int: "int", float: "float", bool: "bool"}.get(o.type, "string")


def node_options() -> list[dict[str, Any]]:
    """GET /options: the table's project options and the check points, five keys each."""
    out = []
    for name in PROJECT_OPTIONS:
        o = OPTIONS[name]
        out.append(
            {
                "name": node_name(name),
                "type": _type(o),
                "value": str(NODE_DEFAULTS.get(name, o.default)),
                "domain": _domain(o),
                "help": o.help,
            }
        )
    out.append(
        {
            "name": CHECKPOINTS,
            "type": "string",
            "value": "",
            "domain": "count or names",
            "help": CHECKPOINTS_HELP,
        }
    )
    return out


@dataclass(frozen=True)
class TaskOptions:
    """A task's options as the node took them: ``given`` the known ones as sent (what task info
    echoes), ``project`` for the match job, ``checkpoints`` for the reconstruct job."""

    given: list[dict[str, Any]]
    project: dict[str, Any]
    checkpoints: list[str] | int | None = None


def _typed(o: Option, value: Any) -> Any:
    """``value`` in its option's type: WebODM's form sends text ("640", "true")."""
    if isinstance(value, str) and o.type in (int, float) and not o.choices:
        text = value.strip()
        try:
            return int(text) if o.type is int else float(text)
        except ValueError:
            return value  # the option's check names it
    return value


def _checkpoints(value: Any) -> list[str] | int | None:
    if value is None or value == "":
        return None
    if isinstance(value, bool):
        raise InvalidRequest(f"checkpoints must be a count or point names, not {value!r}")
    if isinstance(value, int):
        return value
    if isinstance(value, list):
        return [str(v) for v in value]
    text = str(value).strip()
    if text.isdigit():
        return int(text)
    return [n.strip() for n in text.split(",") if n.strip()]


def parse_options(raw: str | None) -> TaskOptions:
    """A task's ``options`` form field (NodeODM's JSON list of ``{name, value}``)."""
    if raw is None or not raw.strip():
        return TaskOptions([], dict(NODE_DEFAULTS))
    try:
        items = json.loads(raw)
    except ValueError as e:
        raise InvalidRequest(f"options must be a JSON list of {{name, value}}: {e}") from None
    if isinstance(items, dict):  # {name: value}, as some scripts send it
        items = [{"name": k, "value": v} for k, v in items.items()]
    if not isinstance(items, list) or not all(isinstance(i, dict) and "name" in i for i in items):
        raise InvalidRequest("options must be a JSON list of {name, value}")
    known = {node_name(n): n for n in NODE_OPTIONS}
    given: list[dict[str, Any]] = []
    project: dict[str, Any] = {}
    checkpoints = None
    for item in items:
        name = known.get(str(item["name"]).strip())
        if name is None:
            continue  # an option of another engine: dropped, as NodeODM drops what it does not know
        value = item.get("value")
        given.append({"name": node_name(name), "value": value})
        if name == CHECKPOINTS:
            checkpoints = _checkpoints(value)
            continue
        o = OPTIONS[name]
        try:
            project[name] = o.check(_typed(o, value))
        except OptionError as e:
            raise InvalidRequest(f"option {node_name(name)}: {e}") from None
    return TaskOptions(given, NODE_DEFAULTS | project, checkpoints)
