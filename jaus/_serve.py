"""``ups jaus --listen HOST:PORT --id S.N.C --map FILE (--can BUS | --broker | --zenoh)``: run
a ``JausHost`` on a node of the robot's network until a signal."""

from __future__ import annotations

import argparse
import logging
import os

from ups import ConfigError
from ups._address import parse_address
from ups._cliargs import node_for, say
from ups._metrics import Reading, serving_metrics

from ._codec import JausId
from ._host import JausHost
from ._judp import JUDP_PORT
from ._mapping import Bridge
from ._metrics import jaus_reading

log = logging.getLogger("ups.jaus")


def parse_judp_address(text: str) -> tuple[str, int]:
    """``HOST:PORT``, or ``HOST`` on JUDP's port 3794."""
    host, port = parse_address(text)
    _, colon, last = text.rpartition(":")
    return (host, port) if colon and "]" not in last else (host, JUDP_PORT)


def bind_error(where: str, exc: OSError) -> ConfigError:
    """One line for a UDP socket that cannot be bound: the system's reason (uvloop puts it in
    the cause, under a message showing a Python tuple)."""
    cause = exc.__cause__ if isinstance(exc.__cause__, OSError) else exc
    why = cause.strerror or (os.strerror(cause.errno) if cause.errno else str(cause))
    return ConfigError(f"cannot listen on {where} (UDP): {why}")


def parse_jaus_id(text: str) -> JausId:
    try:
        subsystem, node, component = (int(part, 0) for part in text.split("."))
        return JausId(subsystem, node, component)
    except ValueError:
        raise ConfigError(f"a JAUS id is subsystem.node.component, e.g. 1.1.1: {text!r}") from None


async def serve(args: argparse.Namespace, bridge: Bridge) -> int:
    me = parse_jaus_id(args.id)
    host, port = parse_judp_address(args.listen)
    kind, node = node_for(args, "ups-jaus")
    component: JausHost | None = None  # its counters are served once it exists

    def reading() -> Reading:
        return [] if component is None else jaus_reading(component, node, kind)

    async with serving_metrics(getattr(args, "metrics", None), "jaus", reading), node:
        component = JausHost(node, bridge, me, name=args.name, authority=args.authority)
        try:
            bound = await component.start(host or "0.0.0.0", port)
        except OSError as exc:
            raise bind_error(f"{host or '0.0.0.0'}:{port}", exc) from None
        face = node.face
        if hasattr(face, "extra_status"):  # TCP and Zenoh nodes answer `ups status`
            face.extra_status = component.status
        say(args, f"JAUS component {me} on {bound[0]}:{bound[1]} (JUDP and RA 3.3)")
        try:
            await component.finished.wait()
            log.info("JAUS component %s shut down by its controlling client", me)
        finally:
            component.close()
            log.info("JAUS component stopping: %s", component.stats())
    return 0
