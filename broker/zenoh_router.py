"""``ups zenoh-router``: a Zenoh router (Zenoh's own, from the ``eclipse-zenoh`` package), for
users who have no ``zenohd``. UPS nodes and gateways on Zenoh are its clients; routers linked
with ``connect`` make one Zenoh network across hosts and sites."""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
from pathlib import Path

from ups._errors import ConfigError

log = logging.getLogger("ups.zenoh")


async def serve(listen: list[str], connect: list[str], config: str | Path | None = None) -> None:
    """Run a Zenoh router listening on ``listen`` and linked to the routers at ``connect``
    until cancelled. ``config`` (a Zenoh JSON5 file: TLS, authentication, access control) is
    read first; the endpoints given here are added to it."""
    from ups._zenohface import zenoh_config

    conf = zenoh_config("", config, mode="router")  # first: it says when Zenoh is missing
    import zenoh

    try:
        conf.insert_json5("mode", json.dumps("router"))
        conf.insert_json5("listen/endpoints", json.dumps(listen))
        if connect:
            conf.insert_json5("connect/endpoints", json.dumps(connect))
    except zenoh.ZError as exc:
        raise ConfigError(f"bad Zenoh endpoint in {listen + connect}: {exc}") from None
    try:
        session = await asyncio.to_thread(zenoh.open, conf)
    except zenoh.ZError as exc:
        raise ConfigError(f"the Zenoh router could not start on {', '.join(listen)}: {exc}"
                          ) from None  # fmt: skip
    try:
        log.info("Zenoh router %s on %s%s", session.zid(), ", ".join(listen),
                 f", linked to {', '.join(connect)}" if connect else "")  # fmt: skip
        await asyncio.Event().wait()
    finally:
        with contextlib.suppress(Exception):
            await asyncio.to_thread(session.close)
