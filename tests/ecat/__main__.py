"""Run emulated EtherCAT slaves on a network interface, for tests:

    python -m tests.ecat --ifname IF --slave vendor=0x2,product=0x7d23052,revision=1,\
name=EL-test,outputs=4,inputs=4 [--slave ...] [--control PATH] [--watchdog S]

The slaves form a line on IF (a raw AF_PACKET socket for EtherType 0x88A4: root, or
CAP_NET_RAW). On stdout, one line per event: ``ready IF N`` once listening, ``state POS NAME
CODE`` when a slave's AL status changes (CODE the AL status code, 0x0000 without error),
``outputs POS HEX`` when a slave's application outputs change. The control socket (a Unix
datagram socket at PATH) takes ``inputs POS HEX`` (set what the slave's inputs read),
``status POS`` (a JSON line back: state, error, code, outputs, inputs, counts) and answers each
with one datagram (``ok``, the JSON, or ``error: ...``). SIGTERM or SIGINT ends it.
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import select
import signal
import socket
import sys
import time
from types import FrameType

from ._chain import ETHERTYPE, Chain
from ._esc import STATE_NAMES, Slave
from ._sii import Identity

PACKET_OUTGOING = 4
MAX_FRAME = 1518
TICK = 0.01  #: seconds between watchdog checks when no frame comes


def identity(text: str) -> Identity:
    fields = dict(part.split("=", 1) for part in text.split(",") if "=" in part)
    known = {"vendor", "product", "revision", "name", "outputs", "inputs", "serial"}
    if set(fields) - known or "vendor" not in fields or "product" not in fields:
        raise argparse.ArgumentTypeError(
            f"bad --slave {text!r}: vendor=N,product=N[,revision,name,outputs,inputs,serial]"
        )
    try:
        return Identity(
            vendor=int(fields["vendor"], 0),
            product=int(fields["product"], 0),
            revision=int(fields.get("revision", "1"), 0),
            name=fields.get("name", "UPS test slave"),
            outputs=int(fields.get("outputs", "4"), 0),
            inputs=int(fields.get("inputs", "4"), 0),
            serial=int(fields.get("serial", "0"), 0),
        )
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"bad --slave {text!r}: {exc}") from None


def say(line: str) -> None:
    sys.stdout.write(line + "\n")
    sys.stdout.flush()


def changed(slave: Slave, what: str, position: int) -> None:
    if what == "state":
        state, _error, code = slave.al_status
        say(f"state {position} {STATE_NAMES.get(state, str(state))} 0x{code:04x}")
    else:
        say(f"outputs {position} {slave.outputs.hex()}")


def control(chain: Chain, text: str) -> str:
    words = text.split()
    try:
        position = int(words[1])
        slave = chain.slaves[position - 1]
        if position < 1:
            raise IndexError
    except (IndexError, ValueError):
        return f"error: which slave? {text!r}"
    if words[0] == "inputs" and len(words) == 3:
        try:
            value = bytes.fromhex(words[2])
        except ValueError:
            return f"error: not hex: {words[2]!r}"
        if len(value) != len(slave.inputs):
            return f"error: slave {position} has {len(slave.inputs)} input bytes"
        slave.inputs[:] = value
        return "ok"
    if words[0] == "status":
        state, error, code = slave.al_status
        return json.dumps({
            "state": STATE_NAMES.get(state, str(state)), "error": error, "code": code,
            "station": slave.station, "outputs": slave.outputs.hex(),
            "inputs": slave.inputs.hex(), "counts": slave.counts, "chain": chain.counts,
        })  # fmt: skip
    return f"error: unknown command {text!r}"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m tests.ecat", description=__doc__)
    parser.add_argument("--ifname", required=True)
    parser.add_argument("--slave", type=identity, action="append", required=True)
    parser.add_argument("--control", metavar="PATH")
    parser.add_argument("--watchdog", type=float, default=0.0, help="SM watchdog, s (0: off)")
    args = parser.parse_args(argv)
    slaves = [
        Slave(ident, watchdog=args.watchdog, on_change=functools.partial(changed, position=n))
        for n, ident in enumerate(args.slave, 1)
    ]
    chain = Chain(slaves)
    wire = socket.socket(socket.AF_PACKET, socket.SOCK_RAW, socket.htons(ETHERTYPE))
    wire.bind((args.ifname, ETHERTYPE))
    sockets = [wire]
    ctl = None
    if args.control:
        ctl = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        ctl.bind(args.control)
        sockets.append(ctl)
    running = True

    def stop(signum: int, frame: FrameType | None) -> None:
        nonlocal running
        running = False

    signal.signal(signal.SIGTERM, stop)
    signal.signal(signal.SIGINT, stop)
    say(f"ready {args.ifname} {len(slaves)}")
    try:
        while running:
            try:
                readable, _, _ = select.select(sockets, [], [], TICK)
            except InterruptedError:
                continue
            if wire in readable:
                try:
                    frame, address = wire.recvfrom(MAX_FRAME)
                except OSError:  # the link went down under us: frames are lost, as on a wire
                    frame, address = b"", ("", 0, PACKET_OUTGOING)
                if address[2] != PACKET_OUTGOING:
                    reply = chain.process(frame)
                    if reply is not None:
                        try:
                            wire.send(reply)
                        except OSError:
                            chain.counts["dropped"] += 1
            if ctl is not None and ctl in readable:
                text, peer = ctl.recvfrom(4096)
                if peer:
                    ctl.sendto(control(chain, text.decode(errors="replace")).encode(), peer)
            now = time.monotonic()
            for slave in slaves:
                slave.tick(now)
    finally:
        wire.close()
        if ctl is not None:
            ctl.close()
            os.unlink(args.control)
    return 0


if __name__ == "__main__":
    sys.exit(main())
