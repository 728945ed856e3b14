"""Every payload this codec knows, by message code: the registry the host, the mapping and
the OCU look messages up in. ``payloads`` is a namespace of all the classes and enums."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

from . import (
    _discovery_payloads,
    _event_payloads,
    _lists,
    _management_payloads,
    _mobility,
    _payloads,
)

MODULES = (_payloads, _management_payloads, _event_payloads, _discovery_payloads, _mobility, _lists)
TYPES: tuple[type, ...] = tuple(kind for module in MODULES for kind in module.TYPES)
PAYLOAD_TYPES: dict[int, type] = {kind.CODE: kind for kind in TYPES}  # type: ignore[attr-defined]
payloads = SimpleNamespace(
    **{
        name: value
        for module in MODULES
        for name, value in vars(module).items()
        if not name.startswith("_")
    }
)


def decode_payload(code: int, payload: bytes) -> Any | None:
    """The payload of message ``code`` decoded, or None when this codec has no decoder for it.
    :class:`JausDecodeError` when the bytes do not fit the code's layout."""
    kind = PAYLOAD_TYPES.get(code)
    return None if kind is None else kind.from_bytes(payload)  # type: ignore[attr-defined]


def encode_payload(payload: Any) -> tuple[int, bytes]:
    """(message code, payload bytes) of ``payload``."""
    return payload.CODE, payload.to_bytes()
