"""The TCP-ECB's liveness sweep: nodes silent for the liveness time leave every list.

Only time in which the ECB could read counts as a node's silence. While its event loop is held
up (a long piece of work, the process not scheduled), live nodes' frames wait unread in their
sockets: a sweep that comes late by more than ``HELD_UP`` credits every node with the time the
loop lost, so that none is judged silent for it (counted in ``held_up``, logged at most once a
second).
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable, Mapping

from ._tcpmember import Member

log = logging.getLogger("ups.tcp_ecb")

HELD_UP = 0.25  #: seconds a liveness sweep may come late before the loop counts as held up


async def sweep(
    members: Mapping[int, Member],
    liveness: float,
    leave: Callable[[Member, str], None],
    counters: dict[str, int],
) -> None:
    """Every quarter of ``liveness``, ``leave`` the members silent for ``liveness`` seconds
    (``member.heard``, ``time.monotonic()``); runs until cancelled."""
    period = liveness / 4
    due = time.monotonic() + period
    logged = float("-inf")  # time.monotonic() of the last log of a held-up loop
    while True:
        await asyncio.sleep(max(0.0, due - time.monotonic()))
        now = time.monotonic()
        late, due = now - due, now + period
        if late > HELD_UP:
            counters["held_up"] += 1
            for member in members.values():  # never past now: heard since, heard now
                member.heard = min(now, member.heard + late)
            if now - logged >= 1.0:
                logged = now
                log.warning(
                    "the TCP-ECB could not run for at least %.1f s; that time does not count as "
                    "nodes' silence (%d times so far)", late, counters["held_up"],
                )  # fmt: skip
        for member in list(members.values()):
            if now - member.heard > liveness:
                try:
                    leave(member, f"silent for {liveness:g} s")
                except Exception:  # one broken entry must not stop every later sweep
                    counters["errors"] += 1
                    log.exception("could not remove node %016x", member.node_id)
