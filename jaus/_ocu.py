"""``ups jaus-ocu``: a small JAUS operator control unit for scripts and tests, printing one
JSON object per line.

::

    ups jaus-ocu discover                   # Query Identification: broadcast, and this host
    ups jaus-ocu query GlobalPose           # of the first component that answers
    ups jaus-ocu --target 127.0.0.1:3794 query GlobalPose
    ups jaus-ocu --target … control request --authority 10
    ups jaus-ocu --target … send SetWrenchEffort propulsive_linear_x=25 --control
    ups jaus-ocu --target … watch GlobalPose --rate 10 --count 20
    ups jaus-ocu --target … waypoints 5,0 5,5 0,5 --speed 1.5

Without ``--target``, Query Identification goes to 255.255.255.255:3794 (the network) and to
127.0.0.1:3794 (a component on this host listening on loopback, as ``ups demo --jaus`` does,
hears no broadcast), or only to ``--broadcast ADDRESS``; ``discover`` prints every component
that answers (once each), the other actions talk to the first (of id ``--to``, when given).

Every command speaks JUDP (``--framing ra33`` for paper 001's RA 3.3 framing) from the JAUS id
``--id`` (default 200.1.1): a component recognises its controller by that id, so ``control
request`` in one command and ``send`` in the next act as one OCU, as long as the second comes
within the component's control timeout. ``send --control`` takes control, resumes, sends and
releases in one go; ``waypoints`` takes control, loads a local waypoint list, executes it and
follows it (one line each time the active waypoint changes) until the robot has reached the
last, keeping control all along, then releases it.

Whatever goes wrong is one line naming the messages as the standard does ("no answer (Report
Global Pose) to Query Global Pose from 127.0.0.1:3794 within 2 s"), and exit 2.
"""

from __future__ import annotations

import argparse
import dataclasses
import enum
import json
import socket
import sys
import time
import typing
from collections.abc import Iterator
from typing import Any

from ups import ConfigError, UpsError

from ._codec import AckNak, JausDecodeError, JausId
from ._codes import message_name
from ._judp import JUDP_PORT, Broadcast, JudpHeader, JudpMessage, decode_judp, encode_judp
from ._lists import ALL_ELEMENTS, Element
from ._messages import PAYLOAD_TYPES, decode_payload, encode_payload
from ._messages import payloads as p
from ._ra33 import RA33_PREFIX, Ra33Address, Ra33Header, Ra33Message, decode_ra33, encode_ra33
from ._ra33_payloads import decode_ra33_payload, encode_ra33_payload

BY_NAME = {cls.__name__: cls for cls in PAYLOAD_TYPES.values()}
EVERYONE = JausId(0xFFFF, 0xFF, 0xFF)
#: where ``discover`` asks by default: the network by broadcast, and this host (a component
#: listening on loopback, as ``ups demo --jaus`` does, hears no broadcast)
DEFAULT_TARGETS = (("255.255.255.255", JUDP_PORT), ("127.0.0.1", JUDP_PORT))
MAX_EVENT_RATE = 1092.0  #: Hz: Create Event's rate field, scaled 0..1092


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
            f"no answer ({' or '.join(_named(a) for a in typing.get_args(answer) or (answer,))})"
            f" to {_named(type(payload))} from {self.where()} within {self.timeout:g} s"
        )


def _named(cls: type) -> str:
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


def build(name: str, assignments: list[str]) -> Any:
    """A message named ``name`` from ``FIELD=VALUE`` texts (numbers, enum names or values)."""
    cls = BY_NAME.get(name)
    if cls is None:
        raise ConfigError(f"unknown JAUS message {name!r}")
    hints = typing.get_type_hints(cls)
    values: dict[str, Any] = {}
    for text in assignments:
        key, sep, raw = text.partition("=")
        if not sep or key not in hints:
            fields = ", ".join(f.name for f in dataclasses.fields(cls))
            raise ConfigError(f"{name}: give FIELD=VALUE, fields: {fields}")
        values[key] = _convert(hints[key], raw, f"{name}.{key}")
    required = [
        f.name
        for f in dataclasses.fields(cls)
        if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING
    ]
    missing = [f"{key}=VALUE" for key in required if key not in values]
    if missing:
        raise ConfigError(f"{name} needs {', '.join(missing)}")
    try:
        message = cls(**values)
        encode_payload(message)
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{name}{_culprit(cls, values, required)}: {exc}") from None
    return message


def _culprit(cls: type, values: dict[str, Any], required: list[str]) -> str:
    """``.FIELD=VALUE`` of the first value that cannot be sent alone (with 0 in every other
    required field), or nothing when none is to blame alone."""
    for key, value in values.items():
        try:
            encode_payload(cls(**{**dict.fromkeys(required, 0), key: value}))
        except (TypeError, ValueError):
            return f".{key}={value}"
    return ""


def _convert(hint: Any, raw: str, what: str) -> Any:
    for kind in typing.get_args(hint) or (hint,):
        try:
            if isinstance(kind, type) and issubclass(kind, enum.Enum):
                return kind[raw] if raw in kind.__members__ else kind(int(raw, 0))
            if kind is int:
                return int(raw, 0)
            if kind is float:
                return float(raw)
            if kind is str:
                return raw
        except (ValueError, KeyError):
            continue
    raise ConfigError(f"{what}: cannot read {raw!r}")


def _query_of(topic: str) -> Any:
    """Query<topic>, asking for every field (the query's default presence vector)."""
    cls = BY_NAME.get(f"Query{topic.removeprefix('Query').removeprefix('Report')}")
    if cls is None:
        raise ConfigError(f"no Query message for {topic!r}")
    try:
        return cls()
    except TypeError:
        raise ConfigError(f"{_named(cls)} needs fields: send {cls.__name__} FIELD=VALUE") from None


def run(args: argparse.Namespace) -> int:
    """One action; without --target, the component is found first (``_find``)."""
    from ._serve import parse_jaus_id, parse_judp_address

    me = parse_jaus_id(args.id)
    to = parse_jaus_id(args.to) if args.to else None
    if args.target:
        targets = [parse_judp_address(args.target)]
    else:
        targets = [(args.broadcast, JUDP_PORT)] if args.broadcast else list(DEFAULT_TARGETS)
    ocu = Ocu(me, targets, ra33=args.framing == "ra33", broadcast=not args.target,
              timeout=args.timeout)  # fmt: skip
    try:
        if not args.target and args.ocu_command != "discover":
            to, address = _find(ocu, to)
            ocu.targets = [address]
        return _ACTIONS[args.ocu_command](ocu, to, args)
    except UpsError:
        raise
    except ValueError as exc:  # a value JAUS cannot carry: one line, no traceback
        raise ConfigError(str(exc)) from None
    finally:
        ocu.close()


def _identify(ocu: Ocu, to: JausId | None) -> Iterator[tuple[JausId, Any, tuple[str, int]]]:
    """Every Report Identification that answers one Query Identification within the timeout,
    each component once (one on this host that hears the broadcast answers twice)."""
    ocu.send(p.QueryIdentification(p.QueryType.COMPONENT), to)
    until, seen = time.monotonic() + ocu.timeout, set()
    while (got := ocu.receive(until)) is not None:
        source, payload, addr = got
        if not isinstance(payload, p.ReportIdentification):
            continue
        key = (source, payload.identification, addr[1])
        if key not in seen:
            seen.add(key)
            yield got


def _nobody(ocu: Ocu) -> str:
    asked = ocu.where()
    if ocu.unreachable:
        asked += "; " + "; ".join(f"{h}:{p}: {why}" for (h, p), why in ocu.unreachable.items())
    return f"no JAUS component answered Query Identification within {ocu.timeout:g} s ({asked})"


def _find(ocu: Ocu, to: JausId | None) -> tuple[JausId, tuple[str, int]]:
    """The first component that answers (``to``, when given), and its address."""
    for source, _, address in _identify(ocu, to):
        if to is None or source == to:
            return source, address
    raise ConfigError(f"{_nobody(ocu)}: give --target HOST:PORT")


def _discover(ocu: Ocu, to: JausId | None, args: argparse.Namespace) -> int:
    found = 0
    for source, payload, addr in _identify(ocu, to):
        found += 1
        print(
            json.dumps(
                {
                    "id": str(source),
                    "address": f"{addr[0]}:{addr[1]}",
                    "name": payload.identification,
                    "type": int(payload.identification_type),
                }
            ),
            flush=True,
        )
    if not found:
        print(f"ups jaus-ocu: {_nobody(ocu)}", file=sys.stderr)
    return 0 if found else 1


def _query(ocu: Ocu, to: JausId | None, args: argparse.Namespace) -> int:
    query = _query_of(args.message)
    answer = BY_NAME[type(query).__name__.replace("Query", "Report", 1)]
    source, report = ocu.ask(query, answer, to)
    print(to_json(source, report), flush=True)
    return 0


def _control(ocu: Ocu, to: JausId | None, args: argparse.Namespace) -> int:
    if args.action == "request":
        source, reply = ocu.ask(p.RequestControl(args.authority), p.ConfirmControl, to)
    elif args.action == "release":
        source, reply = ocu.ask(p.ReleaseControl(), p.RejectControl, to)
    else:
        source, reply = ocu.ask(p.QueryControl(), p.ReportControl, to)
    print(to_json(source, reply), flush=True)
    granted = not isinstance(reply, p.ConfirmControl) or reply.response == 0
    return 0 if granted else 1


def _send(ocu: Ocu, to: JausId | None, args: argparse.Namespace) -> int:
    message = build(args.message, args.fields)
    if args.control:
        source, reply = ocu.ask(p.RequestControl(args.authority), p.ConfirmControl, to)
        print(to_json(source, reply), flush=True)
        if reply.response != 0:
            return 1
        ocu.send(p.Resume(), to)
    ocu.send(message, to)
    if args.control:
        ocu.ask(p.QueryStatus(), p.ReportStatus, to)  # carried out by now: then let go
        source, reply = ocu.ask(p.ReleaseControl(), p.RejectControl, to)
    print(json.dumps({"sent": args.message}), flush=True)
    return 0


def _watch(ocu: Ocu, to: JausId | None, args: argparse.Namespace) -> int:
    if args.rate > MAX_EVENT_RATE:
        raise ConfigError(f"--rate is at most {MAX_EVENT_RATE:g} Hz (Create Event's range)")
    query = _query_of(args.message)
    code, body = encode_payload(query)
    kind = 1 if args.change else 0
    create = p.CreateEvent(1, p.EventType(kind), args.rate, code.to_bytes(2, "little") + body)
    _, confirm = ocu.ask(create, p.ConfirmEventRequest | p.RejectEventRequest, to)
    if isinstance(confirm, p.RejectEventRequest):
        print(to_json(to or EVERYONE, confirm), flush=True)
        return 1
    shown = 0
    try:
        while args.count is None or shown < args.count:
            got = ocu.receive(time.monotonic() + max(ocu.timeout, 2 / max(args.rate, 0.1)))
            if got is None:
                print(json.dumps({"error": "no event within the timeout"}), file=sys.stderr)
                return 1
            source, payload, _ = got
            if isinstance(payload, p.Event) and payload.event_id == confirm.event_id:
                msg = payload.report_message
                report = decode_payload(int.from_bytes(msg[:2], "little"), msg[2:])
                print(to_json(source, report), flush=True)
                shown += 1
    finally:
        ocu.send(p.CancelEvent(2, confirm.event_id), to)
    return 0


def _waypoints(ocu: Ocu, to: JausId | None, args: argparse.Namespace) -> int:
    if ocu.ra33:
        raise ConfigError("waypoints needs --framing judp: the List Manager's messages are "
                          "served in JUDP only")  # fmt: skip
    if args.tolerance is not None and args.tolerance > 100:
        raise ConfigError("--tolerance is at most 100 m (Set Local Waypoint's range)")
    if args.speed > 327.67:
        raise ConfigError("--speed is at most 327.67 m/s (Execute List's range)")
    elements = []
    for i, text in enumerate(args.points):
        try:
            x, y = (float(v) for v in text.split(","))
        except ValueError:
            raise ConfigError(f"a waypoint is X,Y in metres, not {text!r}") from None
        if not (abs(x) <= 100000 and abs(y) <= 100000):
            raise ConfigError(f"waypoint {text}: x and y are -100000..100000 m in JAUS")
        code, body = encode_payload(p.SetLocalWaypoint(x, y, waypoint_tolerance=args.tolerance))
        after = i + 2 if i + 1 < len(args.points) else 0
        elements.append(Element(i + 1, i, after, code.to_bytes(2, "little") + body))
    source, reply = ocu.ask(p.RequestControl(args.authority), p.ConfirmControl, to)
    print(to_json(source, reply), flush=True)
    if reply.response != 0:
        return 1
    answered = p.ConfirmElementRequest | p.RejectElementRequest
    try:
        ocu.send(p.Resume(), to)
        _, status = ocu.ask(p.QueryStatus(), p.ReportStatus, to)
        if status.status != p.ManagementStatus.READY:  # the list would not run
            print(json.dumps({"error": f"the component is {status.status.name}, not READY"}))
            return 1
        ocu.ask(p.DeleteElement(1, (ALL_ELEMENTS,)), answered, to)
        source, reply = ocu.ask(p.SetElement(2, tuple(elements)), answered, to)
        print(to_json(source, reply), flush=True)
        if isinstance(reply, p.RejectElementRequest):
            return 1
        ocu.send(p.ExecuteList(args.speed), to)
        shown = None
        while True:  # asking keeps control: it lapses after 5 s of silence
            _, active = ocu.ask(p.QueryActiveElement(), p.ReportActiveElement, to)
            if active.uid != shown:
                shown = active.uid
                print(json.dumps({"active": active.uid}), flush=True)
            if active.uid == 0:
                return 0
            time.sleep(args.poll)
    finally:  # sent, not awaited: a robot gone silent must not hide why we stopped
        ocu.send(p.ReleaseControl(), to)


_ACTIONS = {
    "discover": _discover,
    "query": _query,
    "control": _control,
    "send": _send,
    "watch": _watch,
    "waypoints": _waypoints,
}
