"""The link of ``ups jaus-ocu`` (``_ocu``) to a component: one UDP socket, messages sent in
one framing and read back, and the one-line reasons it gives when the component refuses it,
built from what the component itself reports (its status, its controller, its control
timeout)."""

from __future__ import annotations

import dataclasses
import enum
import json
import socket
import time
import typing
from typing import Any

from ups import ConfigError

from ._codec import AckNak, JausDecodeError, JausId
from ._codes import message_name
from ._judp import Broadcast, JudpHeader, JudpMessage, decode_judp, encode_judp
from ._messages import decode_payload, encode_payload
from ._messages import payloads as p
from ._ra33 import RA33_PREFIX, Ra33Address, Ra33Header, Ra33Message, decode_ra33, encode_ra33
from ._ra33_payloads import decode_ra33_payload, encode_ra33_payload

EVERYONE = JausId(0xFFFF, 0xFF, 0xFF)
NOBODY = JausId(0, 0, 0)  #: Report Control's controller when nobody controls
#: commands a component carries out from anyone, not only from the OCU that holds control
#: (AS5710A: AccessControl's own, Management's emergencies, the Events service's, answers)
FREE_COMMANDS = frozenset(
    (0x000D, 0x000E, 0x000F, 0x0010, 0x0006, 0x0007, 0x01F0, 0x01F1, 0x01F2, 0x01F3, 0x01F4,
     0x01F6, 0x041C, 0x041D, 0x0B00)
)  # fmt: skip


class Ocu:
    """One OCU socket: sends messages in one framing to its targets, reads what comes back."""

    def __init__(
        self,
        me: JausId,
        targets: list[tuple[str, int]],
        *,
        ra33: bool,
        broadcast: bool,
        timeout: float,
    ) -> None:
        self.me, self.targets, self.ra33, self.broadcast = me, targets, ra33, broadcast
        self.timeout = timeout
        self.unreachable: dict[tuple[str, int], str] = {}  # targets a send could not reach
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        if broadcast:
            self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_BROADCAST, 1)
        self.sock.bind(("0.0.0.0", 0))
        self._sequence = 0

    def close(self) -> None:
        self.sock.close()

    def where(self) -> str:
        return " and ".join(f"{host}:{port}" for host, port in self.targets)

    def send(self, payload: Any, to: JausId | None = None) -> None:
        to = to or EVERYONE
        self._sequence = (self._sequence + 1) & 0xFFFF
        if self.ra33:
            code, body = encode_ra33_payload(payload)
            dest = Ra33Address(
                min(to.subsystem, 0xFF), to.node, to.component, 0xFF if to == EVERYONE else 1
            )
            me = Ra33Address(self.me.subsystem, self.me.node, self.me.component)
            ra_header = Ra33Header(code, dest, me, sequence=self._sequence)
            datagram = encode_ra33(Ra33Message(ra_header, body))
        else:
            code, body = encode_payload(payload)
            header = JudpHeader(
                destination=to,
                source=self.me,
                sequence=self._sequence,
                broadcast=Broadcast.GLOBAL if to == EVERYONE else Broadcast.NONE,
            )
            datagram = encode_judp([JudpMessage(header, code, body)])
        sent = 0
        for target in self.targets:
            try:
                self.sock.sendto(datagram, target)
                sent += 1
            except OSError as exc:  # a broadcast with no network to go out on, say
                self.unreachable[target] = exc.strerror or str(exc)
        if not sent:
            why = "; ".join(f"{h}:{p}: {text}" for (h, p), text in self.unreachable.items())
            raise ConfigError(f"cannot send to {why}")

    def receive(self, until: float) -> tuple[JausId, Any, tuple[str, int]] | None:
        """The next message decoded (its sender's id, payload and address), or None at
        ``until`` (a time.monotonic() value). Datagrams this codec cannot read are skipped."""
        while (left := until - time.monotonic()) > 0:
            self.sock.settimeout(left)
            try:
                data, addr = self.sock.recvfrom(65536)
            except TimeoutError:
                return None
            except ConnectionRefusedError:  # an ICMP "port unreachable" from a target
                continue
            try:
                if data.startswith(RA33_PREFIX):
                    m = decode_ra33(data)
                    if m.header.ack_nak != AckNak.NONE:
                        continue
                    src = m.header.source
                    payload = decode_ra33_payload(m.header.command_code, m.data)
                    source = JausId(src.subsystem, src.node, src.component)
                else:
                    (msg, *_) = decode_judp(data)
                    if msg.code is None:
                        continue
                    payload = decode_payload(msg.code, msg.payload)
                    source = msg.header.source
            except JausDecodeError:
                continue
            if payload is not None:
                return source, payload, addr
        return None

    def ask(self, payload: Any, answer: Any, to: JausId | None) -> tuple[JausId, Any]:
        self.send(payload, to)
        until = time.monotonic() + self.timeout
        while (got := self.receive(until)) is not None:
            if isinstance(got[1], answer):
                return got[0], got[1]
        raise ConfigError(
            f"no answer ({' or '.join(named(a) for a in typing.get_args(answer) or (answer,))})"
            f" to {named(type(payload))} from {self.where()} within {self.timeout:g} s"
        )


def named(cls: type) -> str:
    """A message's name as the standard writes it: "Report Global Pose"."""
    code = getattr(cls, "CODE", None)
    return (message_name(code) if code is not None else None) or cls.__name__


def to_json(source: JausId, payload: Any) -> str:
    def plain(value: Any) -> Any:
        if isinstance(value, enum.Enum):
            return value.name
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            return {f.name: plain(getattr(value, f.name)) for f in dataclasses.fields(value)}
        if isinstance(value, tuple | list):
            return [plain(v) for v in value]
        if isinstance(value, bytes):
            return value.hex()
        return value

    return json.dumps(
        {"from": str(source), "message": type(payload).__name__, "fields": plain(payload)}
    )


def needs_control(payload: Any) -> bool:
    """Whether a component carries ``payload`` out only from the OCU that holds control: a
    command (code below 0x2000) that is not one of ``FREE_COMMANDS``."""
    code = int(payload.CODE)
    return code < 0x2000 and code not in FREE_COMMANDS


# --- why the component refused -----------------------------------------------------------


def controller(ocu: Ocu, to: JausId | None) -> str:
    """Who controls the component, as a reason: "nobody controls it", "200.1.1 (this OCU's
    --id) controls it from another address, ...", "42.1.2 controls it at authority 50"."""
    return _controller(ocu, to)[0]


def _controller(ocu: Ocu, to: JausId | None) -> tuple[str, bool]:
    """:func:`controller`, and whether another OCU's id controls it."""
    _, report = ocu.ask(p.QueryControl(), p.ReportControl, to)
    holder = JausId(report.subsystem, report.node, report.component)
    if holder == NOBODY:
        return "nobody controls it", False
    if holder != ocu.me:
        return f"{holder} controls it at authority {report.authority}", True
    _, timeout = ocu.ask(p.QueryTimeout(), p.ReportTimeout, to)
    lapse = f"{timeout.timeout} s after" if timeout.timeout else "when"
    return (
        f"{holder} (this OCU's --id) controls it from another address: the control an earlier "
        f"run took, which lapses {lapse} that run's last message"
    ), False


def control_refused(ocu: Ocu, to: JausId | None, source: JausId, reply: Any) -> str:
    """Why Request Control was not granted, in one line."""
    if reply.response == p.ControlResponse.INSUFFICIENT_AUTHORITY:
        return (
            f"{source} grants no control to this OCU: its --authority is below the component's "
            f"minimum, or its address may take no control"
        )
    try:
        _, status = ocu.ask(p.QueryStatus(), p.ReportStatus, to)
        if status.status in (p.ManagementStatus.EMERGENCY, p.ManagementStatus.SHUTDOWN,
                             p.ManagementStatus.FAILURE):  # fmt: skip
            return f"{source} is in {status.status.name} and grants no control"
        who, other = _controller(ocu, to)
    except ConfigError:  # it answers no question about it: the answer alone, then
        return f"{source} answered {reply.response.name}"
    higher = ", and only a higher authority takes control from it" if other else ""
    return f"control of {source} is not available: {who}{higher}"


__all__ = [
    "EVERYONE",
    "FREE_COMMANDS",
    "Ocu",
    "control_refused",
    "controller",
    "named",
    "needs_control",
    "to_json",
]
