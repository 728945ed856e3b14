"""Asking a TCP daemon (a TCP-ECB, a gateway, a node's listening port) for its Status, as
``ups status`` and the operators' tools do: one connection, one StatusRequest."""

from __future__ import annotations

import asyncio
import re
from typing import Any

from . import _tcpwire as w
from ._address import parse_address
from ._errors import AccessDenied, BrokerUnavailable, ConfigError, DecodeError
from ._tls import Tls
from ._tlsprobe import mismatch


async def query_status(
    address: str, timeout: float = 5.0, tls: Tls | None = None
) -> dict[str, Any]:
    """Ask the TCP-ECB, gateway or node listening at ``address`` for its tables and counters."""
    host, port = parse_address(address)
    try:
        async with asyncio.timeout(timeout):
            reader, writer = await asyncio.open_connection(
                host, port, ssl=tls.client() if tls else None
            )
            try:
                writer.write(w.encode(w.StatusRequest()))
                decoder = w.Decoder(max_frame=w.MAX_BODY)
                while data := await reader.read(1 << 16):
                    for frame in decoder.feed(data):
                        if isinstance(frame, w.Status):
                            return frame.info
                        if isinstance(frame, w.Refused):
                            raise AccessDenied(
                                f"{host}:{port} does not show its status: {frame.reason}",
                                "",
                                frame.right,
                            )
            finally:
                writer.close()
    except (OSError, TimeoutError, DecodeError) as exc:  # a TLS record is not a UPS frame
        failed: BaseException | None = exc
        reason = re.sub(r"^\[Errno -?\d+\] ", "", str(exc)) or "timed out"
    else:
        failed, reason = None, "it closed the link without a status"
    if not isinstance(failed, ConnectionRefusedError | TimeoutError):  # TLS on one side only?
        why = await mismatch(host, port, tls, "the daemon")
        if why is not None:
            raise ConfigError(why)
    raise BrokerUnavailable(f"no status from {host}:{port}: {reason}")
