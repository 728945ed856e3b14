"""The map file: which UPS channel each ROS 2 topic stands for, field by field (paper 003's
textual mapping of application messages, in TOML)::

    catalog = "robots.toml"            # the channel catalog, relative to this file
    node = "ups_bridge"                # how the bridge appears in the ROS graph
    namespace = "/"
    domain = 0                         # default: $ROS_DOMAIN_ID, else 0
    distro = "jazzy"                   # jazzy: RIHS01 type hashes; humble: none
    types = { "ups_demo/msg/Wheels" = "Wheels.msg" }   # messages of the map's own

    [topic."/robot/speed"]
    channel = "robot/speed"            # a catalog channel, by name or 0xUID
    type = "std_msgs/msg/Int16"        # pkg/msg/Type
    direction = "to_ros"               # to_ros, from_ros or both
    qos = "sensor_data"                # default, sensor_data, or { reliability, history, depth }
    fields.data = { field = "speed", scale = 1.0, offset = 0.0 }  # catalog = ros*scale+offset
    constants = { }                    # ROS fields given a fixed value
    ups_constants = { }                # catalog fields given a fixed value (towards UPS)
    stamp = "header.stamp"             # a builtin_interfaces/Time: the event's time (to ROS)
    max_rate = 100                     # from ROS: samples a second at most (default 100)
    burst = 20                         # from ROS: samples back to back after a silence (20)

A ROS field left out is zero (an empty string, an empty sequence). Towards UPS every field of
the channel must be mapped or in ``ups_constants``. :func:`load_map` checks all of it once, at
start, and raises :class:`MapError` naming the file and line of the first problem; the result
(``_topic``) converts with compiled structs and plain arithmetic.
"""

from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ups import ConfigError, parse_channel
from ups._catalog import Catalog
from ups._tomlfile import read_toml

from ._admit import DEFAULT_BURST, DEFAULT_RATE, MAX_BURST, MAX_RATE
from ._rmw import DURABILITY, HISTORY, PROFILES, RELIABILITY, Qos
from ._topic import NUMERIC, FieldMap, TopicMap, build_topic
from ._types import PRIMITIVES, STRING, Types, Value, ros_name

DIRECTIONS = ("to_ros", "from_ros", "both")
_TOP = {"catalog", "node", "namespace", "domain", "distro", "types", "topic"}
_KEYS = {"channel", "type", "direction", "qos", "fields", "constants", "ups_constants", "stamp",
         "max_rate", "burst"}  # fmt: skip
_NAME = re.compile(r"[A-Za-z][A-Za-z0-9_]*")
_TOPIC = re.compile(r"/?[A-Za-z_][A-Za-z0-9_]*(/[A-Za-z_][A-Za-z0-9_]*)*")
MAX_DOMAIN = 232
MAX_DEPTH = 10_000  #: the deepest QoS history a topic may ask for (ROS's defaults: 5 and 10)


class MapError(ConfigError):
    """A map that cannot be used; ``str()`` starts with ``FILE:LINE:``."""


@dataclass(frozen=True, slots=True)
class Bridge:
    """A checked map: the bridge's place in the ROS graph and its topics."""

    node: str
    namespace: str
    domain: int
    distro: str
    topics: tuple[TopicMap, ...]
    path: str


def load_map(path: str | Path, catalog: Catalog | None = None, domain: int | None = None) -> Bridge:
    """Read and check the map at ``path``. ``catalog`` replaces the map's; ``domain`` its
    domain (``--domain``)."""
    path = Path(path)
    try:
        text, doc = read_toml(path, "the map")
    except ConfigError as exc:
        raise MapError(str(exc)) from None
    where = _Where(path, text)
    unknown = sorted(set(doc) - _TOP)
    if unknown:
        raise where.error(f"unknown key {unknown[0]!r} ({', '.join(sorted(_TOP))})", unknown[0])
    if catalog is None:
        if "catalog" not in doc:
            raise where.error('no catalog: give catalog = "FILE" or --catalog', None)
        try:
            catalog = Catalog.load(path.parent / str(doc["catalog"]))
        except ConfigError as exc:
            raise where.error(str(exc), "catalog") from None
    node, namespace = doc.get("node", "ups_bridge"), doc.get("namespace", "/")
    if not isinstance(node, str) or not _NAME.fullmatch(node):
        raise where.error(f"node must be a ROS node name (letters, digits, _), not {node!r}",
                          "node")  # fmt: skip
    if not isinstance(namespace, str) or not (
        namespace == "/" or (namespace.startswith("/") and _TOPIC.fullmatch(namespace))
    ):
        raise where.error(f"namespace must be / or /name/..., not {namespace!r}", "namespace")
    if domain is None:
        domain = doc.get("domain", _env_domain())
    if isinstance(domain, bool) or not isinstance(domain, int) or not 0 <= domain <= MAX_DOMAIN:
        raise where.error(f"domain must be 0..{MAX_DOMAIN}, not {domain!r}", "domain")
    distro = doc.get("distro", "jazzy")
    try:
        types = Types(str(distro))
    except ConfigError as exc:
        raise where.error(str(exc), "distro") from None
    own = doc.get("types", {})
    if not isinstance(own, dict):
        raise where.error('types is a table: { "pkg/msg/Type" = "Type.msg" }', "types")
    for name, file in own.items():
        if not isinstance(file, str) or len(ros_name(name).split("/")) != 3:
            raise where.error(f'types: "pkg/msg/Type" = "FILE.msg", not {name} = {file!r}', name)
        try:
            types.add_msg(ros_name(name), path.parent / file)
        except ConfigError as exc:
            raise where.error(str(exc), name) from None
    topics = doc.get("topic", {})
    if not isinstance(topics, dict) or not topics:
        raise where.error('no [topic."/NAME"] table', None)
    built = tuple(
        _topic(name, entry, catalog, types, where, namespace, domain)
        for name, entry in topics.items()
    )
    return Bridge(node, namespace, domain, types.distro, built, str(path))


def _env_domain() -> int | str:
    text = os.environ.get("ROS_DOMAIN_ID", "").strip()
    if not text:
        return 0
    return int(text) if text.isdigit() else text


class _Where:
    """Lines of the file, to name where a problem is."""

    def __init__(self, path: Path, text: str) -> None:
        self.path = path
        self.lines = text.splitlines()

    def line(self, section: str | None, key: str | None) -> int:
        start = 0
        if section is not None:
            header = re.compile(rf"^\s*\[\s*topic\.\s*[\"']?{re.escape(section)}[\"']?\s*\]")
            start = next((i for i, ln in enumerate(self.lines) if header.match(ln)), 0)
        if key is None:
            return start + 1
        pattern = re.compile(rf"(^|[\s.{{,\[\"']){re.escape(key)}[\"']?\s*[=,\]\}}]")
        for i in range(start, len(self.lines)):
            if i > start and section is not None and self.lines[i].lstrip().startswith("["):
                break
            if pattern.search(self.lines[i]):
                return i + 1
        return start + 1

    def error(self, text: str, key: str | None, section: str | None = None) -> MapError:
        return MapError(f"{self.path}:{self.line(section, key)}: {text}")


def _number(value: Any) -> bool:
    """A finite number (inf and nan are no value a map can mean)."""
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


def _topic(
    name: str, entry: Any, catalog: Catalog, types: Types, where: _Where, namespace: str,
    domain: int,
) -> TopicMap:  # fmt: skip
    def fail(text: str, key: str | None = None) -> MapError:
        return where.error(f'[topic."{name}"]: {text}', key, name)

    if not _TOPIC.fullmatch(name):
        raise fail("a topic name is /name/... (letters, digits, _)")
    full = name if name.startswith("/") else f"{namespace.rstrip('/')}/{name}"
    if not isinstance(entry, dict):
        raise fail("must be a table")
    extra = sorted(set(entry) - _KEYS)
    if extra:
        raise fail(f"unknown key {extra[0]!r} ({', '.join(sorted(_KEYS))})", extra[0])
    for key in ("channel", "type"):
        if key not in entry:
            raise fail(f"no {key}")
    try:
        channel = parse_channel(str(entry["channel"]))
    except ConfigError as exc:
        raise fail(str(exc), "channel") from None
    spec = catalog.get(channel.uid)
    if spec is None or not spec.fields:
        raise fail(f"unknown channel {entry['channel']}: the catalog has no payload layout of it",
                   "channel")  # fmt: skip
    type_name = ros_name(str(entry["type"]))
    if not types.known(type_name):
        raise fail(f"unknown type {entry['type']} (standard messages of {types.distro}, or "
                   "one the map's types table defines)", "type")  # fmt: skip
    direction = entry.get("direction", "to_ros")
    if direction not in DIRECTIONS:
        raise fail(f"unknown direction {direction!r} ({', '.join(DIRECTIONS)})", "direction")
    qos = _qos(entry.get("qos", "default"), fail)
    max_rate, burst = _bounds(entry, direction, fail)
    try:
        items = types.items(type_name)
        type_hash = types.type_hash(type_name)
    except ConfigError as exc:
        raise fail(str(exc), "type") from None
    ros = {v.path: v for v in items if isinstance(v, Value)}
    inner = {p.rsplit(".", 1)[0] for p in ros} | {p.split("[")[0] for p in ros if "[" in p}
    ups = {f.name: f for f in spec.fields}
    fields = entry.get("fields", {})
    if not isinstance(fields, dict):
        raise fail("fields must be a table", "fields")
    maps = []
    for path, target in _flat(fields):
        if path not in ros:
            what = "a message, not a value" if path in inner else "unknown field"
            raise fail(f"{what}: {type_name} has no value {path!r} (it has: "
                       f"{', '.join(list(ros)[:12])}{', ...' if len(ros) > 12 else ''})",
                       path.split(".")[-1])  # fmt: skip
        if isinstance(target, str):
            target = {"field": target}
        if (
            not isinstance(target, dict)
            or "field" not in target
            or set(target) - {"field", "scale", "offset"}
        ):
            raise fail(f'fields.{path}: give {{ field = "NAME", scale, offset }}', path)
        field = str(target["field"])
        if field not in ups:
            raise fail(f"unknown field: channel {spec.channel} has no field {field!r} (it has: "
                       f"{', '.join(ups)})", path.split(".")[-1])  # fmt: skip
        value, ufield = ros[path], ups[field]
        numeric = value.type in PRIMITIVES and ufield.type in NUMERIC
        text = value.type == STRING and ufield.type == "str"
        if not (numeric or text):
            raise fail(f"type mismatch: {type_name} {path} ({value.type}) and "
                       f"{spec.channel} {field} ({ufield.type})", path.split(".")[-1])  # fmt: skip
        scale, offset = target.get("scale", 1.0), target.get("offset", 0.0)
        if not (_number(scale) and _number(offset) and math.isfinite(scale)
                and math.isfinite(offset)) or scale == 0:  # fmt: skip
            raise fail(f"fields.{path}: scale (not 0) and offset are finite numbers", path)
        if text and (scale != 1 or offset != 0):
            raise fail(f"fields.{path}: a string has no scale or offset", path)
        maps.append(FieldMap(path, field, float(scale), float(offset)))
    constants = _constants(entry.get("constants", {}), ros, {m.ros for m in maps}, fail,
                           "constants", f"{type_name} has no value")  # fmt: skip
    ups_constants = _constants(entry.get("ups_constants", {}), _as_values(spec.fields), set(),
                               fail, "ups_constants", f"{spec.channel} has no field")  # fmt: skip
    to_ups = direction in ("from_ros", "both")
    if to_ups:
        mapped = [m.ups for m in maps]
        twice = sorted({f for f in mapped if mapped.count(f) > 1})
        if twice:
            raise fail(f"channel field {twice[0]!r} is mapped twice: which ROS value goes to "
                       "UPS?", twice[0])  # fmt: skip
        missing = sorted(set(ups) - set(mapped) - set(ups_constants))
        if missing:
            raise fail(f"towards UPS every field of {spec.channel} needs a value: "
                       f"{missing[0]!r} is neither mapped nor in ups_constants")  # fmt: skip
    stamp = entry.get("stamp")
    if stamp is not None:
        if not isinstance(stamp, str) or {f"{stamp}.sec", f"{stamp}.nanosec"} - set(ros):
            raise fail(f"stamp: {type_name} has no time {stamp!r} (a builtin_interfaces/Time, "
                       "e.g. header.stamp)", "stamp")  # fmt: skip
        if {f"{stamp}.sec", f"{stamp}.nanosec"} & ({m.ros for m in maps} | set(constants)):
            raise fail(f"stamp: {stamp} is filled with the event's time: not mapped nor "
                       "constant", "stamp")  # fmt: skip
    try:
        return build_topic(full, spec, type_name, type_hash, str(direction), qos, items,
                           tuple(maps), constants, ups_constants, stamp, domain,
                           where.line(name, None), max_rate, burst)  # fmt: skip
    except ConfigError as exc:
        raise fail(str(exc)) from None


def _flat(table: dict[str, Any], prefix: str = "") -> list[tuple[str, Any]]:
    """``fields.linear.x = ...`` (TOML nests it) and ``fields."linear.x" = ...`` alike."""
    out: list[tuple[str, Any]] = []
    for key, value in table.items():
        path = f"{prefix}{key}"
        if isinstance(value, dict) and "field" not in value:
            out += _flat(value, f"{path}.")
        else:
            out.append((path, value))
    return out


def _as_values(fields: tuple[Any, ...]) -> dict[str, Value]:
    kinds = {"u8": "uint8", "i8": "int8", "u16": "uint16", "i16": "int16", "u32": "uint32",
             "i32": "int32", "u64": "uint64", "i64": "int64", "f32": "float32",
             "f64": "float64", "bool": "bool", "str": STRING, "bytes": STRING}  # fmt: skip
    return {f.name: Value(f.name, kinds[f.type]) for f in fields}


def _constants(
    table: Any, values: dict[str, Value], mapped: set[str], fail: Any, key: str, none: str
) -> dict[str, Any]:
    if not isinstance(table, dict):
        raise fail(f"{key} is a table", key)
    out = {}
    for path, constant in _flat(table):
        if path not in values:
            raise fail(f"unknown field: {none} {path!r}", path.split(".")[-1])
        if path in mapped:
            raise fail(f"{key}: {path} is mapped: it cannot be constant too", path.split(".")[-1])
        kind = values[path].type
        if kind == STRING:
            if not isinstance(constant, str):
                raise fail(f"type mismatch: {path} is a string, not {constant!r}",
                           path.split(".")[-1])  # fmt: skip
        elif not _number(constant) and not isinstance(constant, bool):
            raise fail(f"type mismatch: {path} is a number ({kind}), not {constant!r}",
                       path.split(".")[-1])  # fmt: skip
        out[path] = constant
    return out


def _bounds(entry: dict[str, Any], direction: str, fail: Any) -> tuple[float, int]:
    """``max_rate`` and ``burst``: what the topic takes from ROS (``_admit``)."""
    if direction == "to_ros":
        given = sorted({"max_rate", "burst"} & set(entry))
        if given:
            raise fail(f"{given[0]} bounds what comes from ROS: this topic only goes to ROS "
                       "(direction from_ros or both)", given[0])  # fmt: skip
    rate = entry.get("max_rate", DEFAULT_RATE)
    if not _number(rate) or not 0 < rate <= MAX_RATE:
        raise fail(f"max_rate is samples a second, above 0 and at most {MAX_RATE:g}, not "
                   f"{rate!r}", "max_rate")  # fmt: skip
    burst = entry.get("burst", DEFAULT_BURST)
    if isinstance(burst, bool) or not isinstance(burst, int) or not 1 <= burst <= MAX_BURST:
        raise fail(f"burst is a number of samples from 1 to {MAX_BURST}, not {burst!r}",
                   "burst")  # fmt: skip
    return float(rate), burst


def _qos(value: Any, fail: Any) -> Qos:
    if isinstance(value, str):
        if value not in PROFILES:
            raise fail(f"qos: {value!r} is not a profile ({', '.join(PROFILES)}, or a table)",
                       "qos")  # fmt: skip
        return PROFILES[value]
    if not isinstance(value, dict) or set(value) - {"reliability", "durability", "history",
                                                    "depth"}:  # fmt: skip
        raise fail("qos is default, sensor_data or { reliability, durability, history, depth }",
                   "qos")  # fmt: skip
    reliability = value.get("reliability", "reliable")
    durability = value.get("durability", "volatile")
    history = value.get("history", "keep_last")
    depth = value.get("depth", 10)
    for label, given, table in (("reliability", reliability, RELIABILITY),
                                ("durability", durability, DURABILITY),
                                ("history", history, HISTORY)):  # fmt: skip
        if given not in table:
            raise fail(f"qos: {label} is one of {', '.join(table)}, not {given!r}", label)
    if isinstance(depth, bool) or not isinstance(depth, int) or not 1 <= depth <= MAX_DEPTH:
        raise fail(f"qos: depth is a number of samples from 1 to {MAX_DEPTH}, not {depth!r}",
                   "depth")  # fmt: skip
    return Qos(RELIABILITY[reliability], DURABILITY[durability], HISTORY[history], depth)
