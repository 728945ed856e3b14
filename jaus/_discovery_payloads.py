"""Payload codecs of Discovery's configuration and services (AS5710A core 1.1 JSIDL:
``QueryClass.xml``, ``InformClass.xml``): which nodes, components and services a subsystem
has. Little-endian; pure functions. ``docs/jaus.md`` ("Payloads") gives the bytes and the
sources.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar, Self

from ._codec import Reader
from ._codes import MessageCode
from ._payloads import _byte


@dataclass(frozen=True, slots=True)
class QueryConfiguration:
    CODE: ClassVar[int] = MessageCode.QUERY_CONFIGURATION
    query_type: int = 2  # subsystem

    def to_bytes(self) -> bytes:
        return _byte(self.query_type, "a query type")

    @classmethod
    def from_bytes(cls, data: bytes) -> Self:
        reader = Reader(data, "QueryConfiguration")
        value = reader.u8()
        reader.end()
        return cls(value)


@dataclass(frozen=True, slots=True)
class Service:
    uri: str
    major: int
    minor: int


@dataclass(frozen=True, slots=True)
class ComponentEntry:
    component: int
    instance: int = 1
    services: tuple[Service, ...] = ()


@dataclass(frozen=True, slots=True)
class NodeEntry:
    node: int
    components: tuple[ComponentEntry, ...]


def _count(items: tuple[object, ...], what: str) -> bytes:
    if len(items) > 0xFF:
        raise ValueError(f"at most 255 {what}")
    return bytes((len(items),))


@dataclass(frozen=True, slots=True)
class ReportConfiguration:
    """Node list (count u8; node id u8, component list (count u8; component id u8, instance
    id u8))."""

    CODE: ClassVar[int] = MessageCode.REPORT_CONFIGURATION
    nodes: tuple[NodeEntry, ...]

    def to_bytes(self) -> bytes:
        out = bytearray(_count(self.nodes, "nodes"))
        for node in self.nodes:
            out += _byte(node.node, "a node id") + _count(node.components, "components")
            for c in node.components:
                out += _byte(c.component, "a component id") + _byte(c.instance, "an instance")
        return bytes(out)

    @classmethod
    def from_bytes(cls, data: bytes) -> Self:
        reader = Reader(data, "ReportConfiguration")
        nodes = []
        for _ in range(reader.u8()):
            node = reader.u8()
            comps = tuple(ComponentEntry(reader.u8(), reader.u8()) for _ in range(reader.u8()))
            nodes.append(NodeEntry(node, comps))
        reader.end()
        return cls(tuple(nodes))


@dataclass(frozen=True, slots=True)
class QueryServices:
    """Node list (count u8, at least 1; node id u8, component list (count u8, at least 1;
    component id u8)); 255 stands for every node or component."""

    CODE: ClassVar[int] = MessageCode.QUERY_SERVICES
    nodes: tuple[tuple[int, tuple[int, ...]], ...] = ((0xFF, (0xFF,)),)

    def to_bytes(self) -> bytes:
        out = bytearray(_count(self.nodes, "nodes"))
        for node, comps in self.nodes:
            out += _byte(node, "a node id") + _count(comps, "components")
            out += b"".join(_byte(c, "a component id") for c in comps)
        return bytes(out)

    @classmethod
    def from_bytes(cls, data: bytes) -> Self:
        reader = Reader(data, "QueryServices")
        nodes = []
        for _ in range(reader.u8()):
            node = reader.u8()
            nodes.append((node, tuple(reader.u8() for _ in range(reader.u8()))))
        reader.end()
        return cls(tuple(nodes))


@dataclass(frozen=True, slots=True)
class ReportServices:
    """Node list (count u8; node id u8, component list (count u8; component id u8, instance id
    u8, service list (count u8; URI: count u8 + bytes, major u8, minor u8)))."""

    CODE: ClassVar[int] = MessageCode.REPORT_SERVICES
    nodes: tuple[NodeEntry, ...]

    def to_bytes(self) -> bytes:
        out = bytearray(_count(self.nodes, "nodes"))
        for node in self.nodes:
            out += _byte(node.node, "a node id") + _count(node.components, "components")
            for c in node.components:
                out += _byte(c.component, "a component id") + _byte(c.instance, "an instance")
                out += _count(c.services, "services")
                for s in c.services:
                    uri = s.uri.encode()
                    if len(uri) > 0xFF:
                        raise ValueError("a service URI is at most 255 bytes")
                    out += bytes((len(uri),)) + uri
                    out += _byte(s.major, "a version") + _byte(s.minor, "a version")
        return bytes(out)

    @classmethod
    def from_bytes(cls, data: bytes) -> Self:
        reader = Reader(data, "ReportServices")
        nodes = []
        for _ in range(reader.u8()):
            node, comps = reader.u8(), []
            for _ in range(reader.u8()):
                component, instance = reader.u8(), reader.u8()
                services = []
                for _ in range(reader.u8()):
                    uri = reader.take(reader.u8()).decode("utf-8", "replace")
                    services.append(Service(uri, reader.u8(), reader.u8()))
                comps.append(ComponentEntry(component, instance, tuple(services)))
            nodes.append(NodeEntry(node, tuple(comps)))
        reader.end()
        return cls(tuple(nodes))


TYPES: tuple[type, ...] = (
    QueryConfiguration,
    ReportConfiguration,
    QueryServices,
    ReportServices,
)
