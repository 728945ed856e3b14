"""A TCP node's watches: the patterns it asked the TCP-ECB to name channels for (Watch), and
what the ECB answers (Names, or Refused with the right "watch"). See docs/protocol.md.

The ECB answers each Watch, in order, with Names frames (the last one ``done``) or a Refused;
later Names frames push channels named since. After a reconnect the node sends its Watches
again, with its registrations.
"""

from __future__ import annotations

import asyncio
import collections
import logging
from collections.abc import Callable

from . import _tcpwire as w
from ._channel import Channel, name_to_uid
from ._errors import AccessDenied, ConfigError
from ._face import Found

log = logging.getLogger("ups.tcp")


class TcpWatches:
    """The patterns a TCP face watches; ``counters`` is the face's (``malformed``: a name the
    ECB gave that is not its UID's)."""

    def __init__(self, counters: dict[str, int], timeout: float) -> None:
        self._counters = counters
        self._timeout = timeout
        self._found: dict[str, Found] = {}  # pattern -> whom to tell of its channels
        #: the Watches sent whose answer has not come, oldest first
        self._pending: collections.deque[tuple[str, asyncio.Future[None]]] = collections.deque()

    @property
    def active(self) -> bool:
        """Whether any pattern is watched."""
        return bool(self._found)

    def frames(self, kind: type[w.Watch | w.Unwatch] = w.Watch) -> list[bytes]:
        """A Watch for every pattern (sent again after a reconnect), or an Unwatch (at close)."""
        return [w.encode(kind(pattern)) for pattern in self._found]

    async def watch(self, pattern: str, found: Found, send: Callable[[bytes], None] | None) -> None:
        """Ask the ECB (``send``: to its link; None while there is none: then the Watch goes
        with the next registration) and wait for its answer, ``timeout`` at most."""
        self._found[pattern] = found
        if send is None:
            log.warning("no TCP-ECB now: the pattern %s is watched once it is back", pattern)
            return
        answered = asyncio.get_running_loop().create_future()
        self._pending.append((pattern, answered))
        send(w.encode(w.Watch(pattern)))
        try:
            await asyncio.wait_for(asyncio.shield(answered), self._timeout)
        except TimeoutError:
            log.warning("the TCP-ECB did not answer the watch of %s within %g s",
                        pattern, self._timeout)  # fmt: skip
        except AccessDenied:
            self._found.pop(pattern, None)
            raise

    def unwatch(self, pattern: str) -> bytes | None:
        """The Unwatch to send, if ``pattern`` was watched."""
        if self._found.pop(pattern, None) is None:
            return None
        return w.encode(w.Unwatch(pattern))

    def names(self, frame: w.Names) -> None:
        found = self._found.get(frame.pattern)
        for uid, name in frame.channels:
            try:
                if name_to_uid(name) != uid:
                    raise ConfigError(name)
            except ConfigError:
                self._counters["malformed"] += 1
                continue
            if found is not None:
                found(Channel(uid, name))
        if frame.done:
            for entry in self._pending:
                if entry[0] == frame.pattern:
                    self._pending.remove(entry)
                    _settle(entry[1], None)
                    break

    def refused(self, frame: w.Refused) -> None:
        """The oldest Watch not answered yet is refused."""
        if self._pending:
            pattern, answered = self._pending.popleft()
            error = AccessDenied(f"the TCP-ECB does not let this node watch {pattern}: "
                                 f"{frame.reason}", pattern, "watch")  # fmt: skip
            _settle(answered, error)

    def close(self) -> None:
        for _, answered in self._pending:
            answered.cancel()
        self._pending.clear()


def _settle(future: asyncio.Future[None], error: BaseException | None) -> None:
    if future.done():
        return
    if error is None:
        future.set_result(None)
    else:
        future.set_exception(error)
        future.exception()  # retrieved: its waiter may have timed out already
