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
``--id`` (default 200.1.1), from a UDP port of its own. ``ups jaus`` binds control to the id
*and* the address it was asked from, so the control one run takes is that run's: ``send
--control`` takes control, resumes, sends, keeps control ``--hold`` seconds and releases it;
``waypoints`` takes control, loads a local waypoint list, executes it and follows it (one line
per waypoint the robot heads for, in order) until the robot has reached the last, keeping
control all along, then releases it (``_ocu_waypoints``). A ``control request`` holds control
until it lapses after that run; meanwhile a run with the same ``--id`` is answered its queries
and refused the rest.

When the component refuses (control not available, an event refused, a command sent without
control), the JSON line of its answer is followed on stderr by one line saying why, from what
the component reports (its status, its controller, its control timeout), and exit 1.
Whatever goes wrong is one line naming the messages as the standard does ("no answer (Report
Global Pose) to Query Global Pose from 127.0.0.1:3794 within 2 s"), and exit 2.
"""

from __future__ import annotations

import argparse
import dataclasses
import enum
import json
import sys
import time
import typing
from collections.abc import Iterator
from typing import Any

from ups import ConfigError, UpsError

from ._codec import JausId
from ._judp import JUDP_PORT
from ._messages import PAYLOAD_TYPES, decode_payload, encode_payload
from ._messages import payloads as p
from ._ocu_link import (
    Ocu,
    control_refused,
    controller,
    named,
    needs_control,
    to_json,
)
from ._ocu_waypoints import waypoints

BY_NAME = {cls.__name__: cls for cls in PAYLOAD_TYPES.values()}
#: where ``discover`` asks by default: the network by broadcast, and this host (a component
#: listening on loopback, as ``ups demo --jaus`` does, hears no broadcast)
DEFAULT_TARGETS = (("255.255.255.255", JUDP_PORT), ("127.0.0.1", JUDP_PORT))
MAX_EVENT_RATE = 1092.0  #: Hz: Create Event's rate field, scaled 0..1092


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
        raise ConfigError(f"{named(cls)} needs fields: send {cls.__name__} FIELD=VALUE") from None


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
    if isinstance(reply, p.ConfirmControl) and reply.response != 0:
        _why(control_refused(ocu, to, source, reply))
        return 1
    if isinstance(reply, p.RejectControl) and reply.response != 0:
        _why(f"nothing to release: this run does not control {source}; {controller(ocu, to)}")
        return 1
    return 0


def _send(ocu: Ocu, to: JausId | None, args: argparse.Namespace) -> int:
    message = build(args.message, args.fields)
    if args.hold and not args.control:
        raise ConfigError("--hold keeps the control that --control takes: give both")
    if not args.control:
        ocu.send(message, to)
        print(json.dumps({"sent": args.message}), flush=True)
        if not needs_control(message):
            return 0
        # handled after the command: a component carries it out only from its controller
        source, _ = ocu.ask(p.QueryStatus(), p.ReportStatus, to)
        _why(f"{named(type(message))} went without control, and {source} carries it out only "
             f"from the OCU that controls it: {controller(ocu, to)}; give --control")  # fmt: skip
        return 1
    source, reply = ocu.ask(p.RequestControl(args.authority), p.ConfirmControl, to)
    print(to_json(source, reply), flush=True)
    if reply.response != 0:
        _why(control_refused(ocu, to, source, reply))
        return 1
    try:
        ocu.send(p.Resume(), to)
        ocu.send(message, to)
        ocu.ask(p.QueryStatus(), p.ReportStatus, to)  # carried out by now
        print(json.dumps({"sent": args.message}), flush=True)
        held = _hold(ocu, to, args.hold) if args.hold else 0
    except BaseException:  # Ctrl-C, or no answer: let go, sent and not awaited (a robot gone
        ocu.send(p.ReleaseControl(), to)  # silent must not hide why we stopped)
        raise
    ocu.ask(p.ReleaseControl(), p.RejectControl, to)
    return held


HOLD_EVERY = 1.0  #: seconds between the questions that keep control while --hold lasts


def _hold(ocu: Ocu, to: JausId | None, seconds: float) -> int:
    """Keep control ``seconds`` (a question every HOLD_EVERY seconds: control lapses after
    the component's timeout of silence); 1 if the component takes it back meanwhile."""
    end = time.monotonic() + seconds
    while (now := time.monotonic()) < end:
        ocu.send(p.QueryStatus(), to)
        until = min(end, now + HOLD_EVERY)
        while (got := ocu.receive(until)) is not None:
            if isinstance(got[1], p.RejectControl):
                _why(f"{got[0]} took control back ({got[1].response.name}) while held")
                return 1
    return 0


def _watch(ocu: Ocu, to: JausId | None, args: argparse.Namespace) -> int:
    if args.rate > MAX_EVENT_RATE:
        raise ConfigError(f"--rate is at most {MAX_EVENT_RATE:g} Hz (Create Event's range)")
    query = _query_of(args.message)
    code, body = encode_payload(query)
    kind = 1 if args.change else 0
    create = p.CreateEvent(1, p.EventType(kind), args.rate, code.to_bytes(2, "little") + body)
    source, confirm = ocu.ask(create, p.ConfirmEventRequest | p.RejectEventRequest, to)
    if isinstance(confirm, p.RejectEventRequest):
        print(to_json(source, confirm), flush=True)
        code_name = confirm.response_code.name if confirm.response_code is not None else "no code"
        said = f": {confirm.error_message}" if confirm.error_message else ""
        _why(f"{source} refused the event ({code_name}){said}")
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


def _why(reason: str) -> None:
    """The one line after a refused answer's JSON: why, on stderr."""
    print(f"ups jaus-ocu: {reason}", file=sys.stderr, flush=True)


_ACTIONS = {
    "discover": _discover,
    "query": _query,
    "control": _control,
    "send": _send,
    "watch": _watch,
    "waypoints": waypoints,
}
