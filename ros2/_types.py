"""ROS 2 message definitions without ROS: the standard messages as rosbags knows them for a
distribution, the map's own ``.msg`` files, their RIHS01 type hashes, and each message
flattened into the values CDR carries, in order.

A message flattens into *items*: ``Value`` (a primitive or a string, with its path such as
``linear.x`` or ``header.frame_id``; the elements of a fixed-size array are ``name[0]``,
``name[1]``, ...) and ``Sequence`` (a variable-length sequence: always sent empty, skipped when
received). Nested messages add nothing of their own to CDR: they flatten into their fields.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ups import ConfigError

from ._rmw import NO_TYPE_HASH

#: ROS primitive types: struct code (little-endian, CDR aligns each to its size)
PRIMITIVES = {
    "bool": "?", "byte": "B", "char": "B", "uint8": "B", "int8": "b", "uint16": "H",
    "int16": "h", "uint32": "I", "int32": "i", "uint64": "Q", "int64": "q", "float32": "f",
    "float64": "d", "octet": "B",
}  # fmt: skip
STRING = "string"
DISTROS = ("jazzy", "humble")  #: jazzy: RIHS01 type hashes; humble: TypeHashNotSupported
_BASE, _NAME, _ARRAY, _SEQUENCE = 1, 2, 3, 4  # rosbags' Nodetype values
MAX_ARRAY = 4096  #: elements of a fixed-size array flattened (larger ones are refused)


@dataclass(frozen=True, slots=True)
class Value:
    """A primitive (``type`` in PRIMITIVES) or a string (``type`` "string") at ``path``."""

    path: str
    type: str
    bound: int = 0  #: a bounded string's most characters (0: unbounded)


@dataclass(frozen=True, slots=True)
class Sequence:
    """A variable-length sequence at ``path`` of ``element``: a primitive type name, "string",
    or the items of one message."""

    path: str
    element: str | tuple[Value | Sequence, ...]


Item = Value | Sequence


class Types:
    """The message definitions of a distribution, and of ``.msg`` files added to them."""

    def __init__(self, distro: str = "jazzy") -> None:
        if distro not in DISTROS:
            raise ConfigError(f"distro must be one of {', '.join(DISTROS)}, not {distro!r}")
        from rosbags.typesys import Stores, get_typestore

        self.distro = distro
        store = Stores.ROS2_JAZZY if distro == "jazzy" else Stores.ROS2_HUMBLE
        self._store: Any = get_typestore(store)

    def add_msg(self, name: str, path: Path) -> None:
        """Define ``name`` (``pkg/msg/Type``) by the ``.msg`` file at ``path``."""
        from rosbags.typesys import get_types_from_msg

        try:
            text = path.read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as exc:
            why = getattr(exc, "strerror", None) or exc
            raise ConfigError(f"cannot read {path}: {why}") from None
        try:
            self._store.register(get_types_from_msg(text, name))
        except Exception as exc:  # rosbags' parser says what it could not read
            raise ConfigError(f"{path} does not define {name}: {exc}") from None

    def known(self, name: str) -> bool:
        return name in self._store.fielddefs

    def type_hash(self, name: str) -> str:
        """``RIHS01_<sha256 in hex>`` of the type (REP-2011), or ``TypeHashNotSupported``."""
        if self.distro == "humble":
            return NO_TYPE_HASH
        try:
            return str(self._store.hash_rihs01(name))
        except Exception as exc:  # a field whose type is defined nowhere
            raise ConfigError(f"{name}: {exc}") from None

    def items(self, name: str, prefix: str = "") -> tuple[Item, ...]:
        """The values of message ``name`` in CDR order, paths under ``prefix``."""
        try:
            _, fields = self._store.fielddefs[name]
        except KeyError:
            raise ConfigError(f"unknown message type {name}") from None
        out: list[Item] = []
        for field, desc in fields:
            out += self._flatten(f"{prefix}{field}", desc)
        return tuple(out)

    def _flatten(self, path: str, desc: Any) -> list[Item]:
        kind, detail = int(desc[0]), desc[1]
        if kind == _BASE:
            base, bound = detail
            if base == STRING:
                return [Value(path, STRING, int(bound or 0))]
            if base not in PRIMITIVES:  # wstring
                raise ConfigError(f"{path}: {base} is not supported")
            return [Value(path, base)]
        if kind == _NAME:
            return list(self.items(detail, f"{path}."))
        if kind == _ARRAY:
            element, length = detail
            if length > MAX_ARRAY:
                raise ConfigError(f"{path}: arrays of more than {MAX_ARRAY} are not supported")
            return [item for i in range(length) for item in self._flatten(f"{path}[{i}]", element)]
        element, _ = detail  # a sequence (bounded or not)
        sub_kind, sub = int(element[0]), element[1]
        if sub_kind == _BASE:
            if sub[0] != STRING and sub[0] not in PRIMITIVES:
                raise ConfigError(f"{path}: sequences of {sub[0]} are not supported")
            return [Sequence(path, str(sub[0]))]
        return [Sequence(path, self.items(sub))]


def ros_name(name: str) -> str:
    """``pkg/Type`` written out as ``pkg/msg/Type`` (both forms are accepted in a map)."""
    parts = name.split("/")
    return f"{parts[0]}/msg/{parts[1]}" if len(parts) == 2 else name
