"""Which language a TCP daemon speaks, for an error that names the real cause when a link to it
fails before it said Hello: TLS where this side spoke plain UPS, or plain UPS where this side
spoke TLS. Each probe is one connection that sends one message and reads one byte, within
``PROBE_TIMEOUT``.

A TLS daemon closes a plain link without a word, and a plain one closes a TLS link at its
first bytes (a TLS record is not a UPS frame), so without a probe both look like "closed by
peer".
"""

from __future__ import annotations

import asyncio
import contextlib
import ssl

from . import _tcpwire as w

PROBE_TIMEOUT = 2.0  #: seconds one probe may take
#: the first byte of a TLS record: handshake (a ServerHello) or alert
_TLS_RECORDS = (b"\x16", b"\x15")


async def mismatch(host: str, port: int, tls: bool, what: str) -> str | None:
    """Why a link to ``what`` at ``host:port`` failed, when it is TLS on one side only: a
    sentence for people, or None when the probe finds no such mismatch."""
    if not tls and await _first_byte(host, port, _client_hello()) in _TLS_RECORDS:
        return (
            f"{what} at {host}:{port} expects TLS: give the fleet's certificates "
            "(--tls-ca, --tls-cert and --tls-key; tls=ups.Tls(...) in Python)"
        )
    if tls and await _first_byte(host, port, w.encode(w.StatusRequest())) == bytes([w.VERSION]):
        return (
            f"{what} at {host}:{port} does not speak TLS (it speaks plain UPS): leave out the "
            "TLS options, or start it with them"
        )
    return None


def _client_hello() -> bytes:
    """The bytes a TLS client opens with (no certificate is checked: nothing is exchanged)."""
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
    context.check_hostname = False
    context.verify_mode = ssl.CERT_NONE
    outgoing = ssl.MemoryBIO()
    tls = context.wrap_bio(ssl.MemoryBIO(), outgoing)
    with contextlib.suppress(ssl.SSLWantReadError):
        tls.do_handshake()
    return outgoing.read()


async def _first_byte(host: str, port: int, message: bytes) -> bytes:
    """The first byte ``host:port`` answers ``message`` with (empty when it closes, or when
    nothing comes within ``PROBE_TIMEOUT``)."""
    try:
        async with asyncio.timeout(PROBE_TIMEOUT):
            reader, writer = await asyncio.open_connection(host, port)
            try:
                writer.write(message)
                return await reader.read(1)
            finally:
                writer.close()
    except (OSError, TimeoutError):
        return b""
