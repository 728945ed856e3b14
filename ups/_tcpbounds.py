"""Bounds on the connections of one listening socket: how many, how long they may wait to be
admitted, how large their frames may be until then (``Doorman``); how many a daemon may hold
(``link_budget``). docs/protocol.md (*Bounds on every listening socket*) says it for people.
"""

from __future__ import annotations

import asyncio
import contextlib
import resource
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from ._tcplink import Link


class Doorman:
    """Bounds the connections one listening socket accepts, and counts what it turns away.

    At most ``max_links`` connections in all. A new one beyond closes the oldest connection
    still waiting to be admitted (``evicted``), or, if none waits, is closed itself
    (``refused``). At most ``max_waiting`` may wait to be admitted: when another comes, the
    oldest waiting one is closed (``evicted``). A connection not admitted (``greeted``) within
    ``hello_timeout`` seconds is closed (``timed_out``). Until ``lift`` or ``greeted``, a
    connection may send frames of at most ``first_frame`` bytes.
    """

    def __init__(
        self,
        max_links: int,
        *,
        max_waiting: int = 256,
        hello_timeout: float = 5.0,
        first_frame: int = 4096,
    ) -> None:
        self.max_links = max_links
        self.max_waiting = max_waiting
        self.hello_timeout = hello_timeout
        self.first_frame = first_frame
        self.links = 0
        self._waiting: dict[Link, asyncio.TimerHandle] = {}  # oldest first
        self.counters = dict.fromkeys(("refused", "evicted", "timed_out"), 0)

    def admit(self, link: Link) -> None:
        """A new connection (call from the protocol factory)."""
        self.links += 1
        if self.links > self.max_links:
            if not self._waiting:
                self.counters["refused"] += 1
                link.abort(f"more than {self.max_links} connections")
                return
            oldest = next(iter(self._waiting))  # one not admitted yet makes room for the new one
            self.counters["evicted"] += 1
            oldest.abort(f"more than {self.max_links} connections, and not admitted")
        if len(self._waiting) >= self.max_waiting:
            oldest = next(iter(self._waiting))
            self.counters["evicted"] += 1
            oldest.abort(f"more than {self.max_waiting} connections without Hello")
        link.max_frame, link.full_frame = self.first_frame, link.max_frame
        loop = asyncio.get_running_loop()
        self._waiting[link] = loop.call_later(self.hello_timeout, self._time_out, link)

    def greeted(self, link: Link) -> None:
        """``link`` said Hello (and is admitted): it may stay, and send full-sized frames."""
        self.lift(link)
        timer = self._waiting.pop(link, None)
        if timer is not None:
            timer.cancel()

    def lift(self, link: Link) -> None:
        """``link`` may send full-sized frames, but still counts as waiting to be admitted
        (``greeted``): it is still timed out, and evicted first."""
        link.max_frame = link.full_frame

    def gone(self, link: Link) -> None:
        """``link`` ended (call from its on_lost)."""
        self.links -= 1
        timer = self._waiting.pop(link, None)
        if timer is not None:
            timer.cancel()

    def _time_out(self, link: Link) -> None:
        if link in self._waiting:
            self.counters["timed_out"] += 1
            link.abort(f"not admitted (no Hello, or none vouched for) within "
                       f"{self.hello_timeout:g} s")  # fmt: skip

    def close(self) -> None:
        for timer in self._waiting.values():
            timer.cancel()
        self._waiting.clear()


def link_budget(ceiling: int = 4096, reserve: int = 64) -> int:
    """How many connections a daemon may hold: ``ceiling``, or fewer if the process's limit on
    open files (raised to its hard limit first) leaves less, ``reserve`` kept for the rest."""
    try:
        soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
        if soft != hard:
            with contextlib.suppress(ValueError, OSError):
                resource.setrlimit(resource.RLIMIT_NOFILE, (hard, hard))
                soft = hard
    except (ValueError, OSError):
        return ceiling
    if soft == resource.RLIM_INFINITY:
        return ceiling
    return max(16, min(ceiling, soft - reserve))
