"""TCP/IP addresses as users write them, and the TCP-ECB's default port: no I/O, cheap to import."""

from __future__ import annotations

from ._errors import ConfigError

DEFAULT_PORT = 7411  #: where a TCP-ECB listens unless told otherwise


def parse_address(text: str, default_host: str = "127.0.0.1") -> tuple[str, int]:
    """``HOST:PORT``, ``HOST`` or ``:PORT`` (IPv6 hosts in brackets) -> (host, port)."""
    host, sep, port = text.rpartition(":")
    if not sep or "]" in port:
        host, port = text, str(DEFAULT_PORT)
    host = host.strip("[]") or default_host
    try:
        number = int(port)
    except ValueError:
        number = -1
    if not 0 <= number <= 0xFFFF:
        raise ConfigError(f"expected HOST:PORT, got {text!r}")
    return host, number
