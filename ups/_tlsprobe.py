"""Which language a TCP daemon speaks, for an error that names the real cause when a link to it
fails before it said Hello: TLS where this side spoke plain UPS, or plain UPS where this side
spoke TLS. Each probe is one connection that sends one message and reads one byte, within
``PROBE_TIMEOUT``.

A TLS daemon closes a plain link without a word, and a plain one closes a TLS link at its
first bytes (a TLS record is not a UPS frame), so without a probe both look like "closed by
peer". So does a TLS daemon that refuses this side's certificate (one signed by another CA):
under TLS 1.3 the client's handshake ends before the server has looked at the client's
certificate, and the server hangs up without an alert. The certificate probe therefore shakes
hands under TLS 1.2, where the server judges the client's certificate inside the handshake:
a handshake that fails on the daemon's certificate is ours refusing it, one cut after ours
was sent is the daemon refusing ours.
"""

from __future__ import annotations

import asyncio
import contextlib
import ssl

from . import _tcpwire as w
from ._tls import Tls

PROBE_TIMEOUT = 2.0  #: seconds one probe may take
#: the first byte of a TLS record: handshake (a ServerHello) or alert
_TLS_RECORDS = (b"\x16", b"\x15")


async def mismatch(host: str, port: int, tls: Tls | None, what: str) -> str | None:
    """Why a link to ``what`` at ``host:port`` failed, when it is TLS on one side only or a
    certificate one side refuses: a sentence for people, or None when the probes find no such
    mismatch."""
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
    if tls:
        return await _refused_certificate(host, port, tls, what)
    return None


async def _refused_certificate(host: str, port: int, tls: Tls, what: str) -> str | None:
    """Which side refused the other's certificate, if one did (TLS 1.2 handshake, see the
    module's text)."""
    context = tls.client()
    context.maximum_version = ssl.TLSVersion.TLSv1_2
    try:
        async with asyncio.timeout(PROBE_TIMEOUT):
            _, writer = await asyncio.open_connection(host, port, ssl=context)
            writer.close()
            return None  # each accepts the other's: not a certificate problem
    except ssl.SSLCertVerificationError as exc:
        why = exc.verify_message or exc.reason or "not verified"
        same_ca = ""
        if exc.verify_code in _OTHER_CA:
            same_ca = (
                ": both sides need certificates from one fleet CA ('ups certs issue DIR NAME')"
            )
        return (
            f"{what} at {host}:{port} shows a certificate that the CA {tls.ca} (--tls-ca) "
            f"does not vouch for ({why}){same_ca}"
        )
    except ssl.SSLError:
        return None  # no TLS 1.2 there, or another disagreement: the caller's own reason
    except (ConnectionRefusedError, TimeoutError):
        return None  # gone, or too busy to shake hands: no verdict on a certificate
    except OSError:  # cut inside the handshake, after ours was sent
        return (
            f"{what} at {host}:{port} refused this side's certificate {tls.cert} (--tls-cert) "
            f"in the TLS handshake: {_signer(tls)}"
        )


#: OpenSSL's verify codes for a certificate no CA given signed
_OTHER_CA = {2, 7, 19, 20, 21}


def _signer(tls: Tls) -> str:
    """Why the daemon refused our certificate, as far as this side can tell (the daemon's own
    certificate passed our check: it comes from our CA)."""
    from cryptography import x509
    from cryptography.exceptions import InvalidSignature

    try:
        ours = x509.load_pem_x509_certificate(tls.cert.read_bytes())
        ca = x509.load_pem_x509_certificate(tls.ca.read_bytes())
        ours.verify_directly_issued_by(ca)
    except (OSError, ValueError, TypeError, InvalidSignature):
        return (
            f"it is not signed by the CA {tls.ca} (--tls-ca), the one the daemon's certificate "
            "comes from: issue this side's with that CA ('ups certs issue DIR NAME')"
        )
    return "it is signed by the CA given, so the daemon trusts another CA, or it has expired"


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
