"""Pattern subscriptions: which of a node's subscriptions watch which globs, the channels each
glob joined as the network named them, and the binding of those channels.

The node's face watches each glob once, however many subscriptions watch it, and calls
``found`` for every named channel it learns of (the TCP-ECB's names, Zenoh keys, a CAN node's
catalog); so does the node for the named channels it uses itself. A channel that a glob
matches joins every subscription watching the glob: it is added to their ``channels``, and
subscribed to on the network if the node was not already. A glob joins at most
``MAX_MATCHES`` channels (more are counted, ``pattern_limited``, and logged once per glob).
A channel the network refuses (an ACL, a bound) is counted (``pattern_refused``), logged,
and left out; the subscription goes on with the others.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import Callable

from ._channel import Channel, matches
from ._errors import Closed, UpsError
from ._face import ChannelState, Face
from ._subscription import Subscription

log = logging.getLogger("ups")

MAX_MATCHES = 4096  #: channels one glob joins at most (then: pattern_limited)


class Watching:
    """The globs a node's subscriptions watch. ``state_of(channel)`` is the node's table entry of
    a channel (made when new), ``face()`` its face."""

    def __init__(
        self, state_of: Callable[[Channel], ChannelState], face: Callable[[], Face]
    ) -> None:
        self._state_of = state_of
        self._face = face
        self._subs: dict[str, list[Subscription]] = {}  # glob -> the subscriptions watching it
        self._joined: dict[str, dict[int, Channel]] = {}  # glob -> the channels it matched
        self._binding: set[asyncio.Task[None]] = set()
        self._limited: set[str] = set()  # globs that hit MAX_MATCHES (logged once)
        self.counters = {"pattern_refused": 0, "pattern_limited": 0}

    @property
    def active(self) -> bool:
        """Whether any subscription watches a glob."""
        return bool(self._subs)

    async def add(self, sub: Subscription) -> None:
        """Watch ``sub.patterns`` for ``sub``: the channels they match now join it, bound on the
        network before this returns; those named later join it as they are."""
        for pattern in sub.patterns:
            subs = self._subs.setdefault(pattern, [])
            subs.append(sub)
            if len(subs) > 1:  # watched already: what it matched joins this one too
                for chan in self._joined[pattern].values():
                    self._join(chan, sub)
                continue
            self._joined[pattern] = {}
            try:
                await self._face().watch(pattern, self.found)
            except BaseException:
                await self.remove(sub)
                raise
        await self.settle()

    async def remove(self, sub: Subscription) -> None:
        """``sub`` no longer watches its globs; the face stops watching those nobody watches."""
        for pattern in sub.patterns:
            subs = self._subs.get(pattern)
            if subs is None or sub not in subs:
                continue
            subs.remove(sub)
            if not subs:
                del self._subs[pattern]
                del self._joined[pattern]
                with contextlib.suppress(UpsError, OSError):
                    await self._face().unwatch(pattern)

    def found(self, chan: Channel) -> None:
        """A named channel is known: it joins the subscriptions whose globs match it."""
        for pattern, subs in self._subs.items():
            joined = self._joined[pattern]
            if chan.uid in joined or not matches(pattern, chan.name):
                continue
            if len(joined) >= MAX_MATCHES:
                self.counters["pattern_limited"] += 1
                if pattern not in self._limited:
                    self._limited.add(pattern)
                    log.warning("%s matches more than %d channels: %s and later ones are left "
                                "out", pattern, MAX_MATCHES, chan)  # fmt: skip
                continue
            joined[chan.uid] = chan
            for sub in subs:
                self._join(chan, sub)

    def _join(self, chan: Channel, sub: Subscription) -> None:
        """Deliver ``chan``'s events to ``sub`` from now on; subscribe on the network if ``sub``
        is the node's first subscriber of it."""
        if sub._closed or any(c.uid == chan.uid for c in sub.channels):
            return
        state = self._state_of(chan)
        if state.channel.name is None:  # known by UID until now: its events carry the name
            state.channel = chan
        sub.channels = (*sub.channels, chan)
        first = not state.subs
        state.subs.append(sub)
        if first:
            task = asyncio.get_running_loop().create_task(self._bind(state))
            self._binding.add(task)
            task.add_done_callback(self._binding.discard)

    async def _bind(self, state: ChannelState) -> None:
        face = self._face()
        try:
            await face.bind(state, subscribe=True)
        except Closed:
            return
        except UpsError as exc:  # refused: an ACL, a bound, no etag left ...
            self.counters["pattern_refused"] += 1
            log.warning("%s matches a pattern, but could not be subscribed to: %s",
                        state.channel, exc)  # fmt: skip
            for sub in [s for s in state.subs if isinstance(s, Subscription) and s.patterns]:
                state.subs.remove(sub)
                sub.channels = tuple(c for c in sub.channels if c.uid != state.channel.uid)
            return
        if not state.subs:  # every subscriber left while it was being bound
            with contextlib.suppress(UpsError, OSError):
                await face.unsubscribe(state)

    async def settle(self) -> None:
        """Wait until the channels joined so far are bound (or refused)."""
        if self._binding:
            await asyncio.gather(*list(self._binding), return_exceptions=True)

    def close(self) -> None:
        for task in self._binding:
            task.cancel()
        self._binding.clear()
