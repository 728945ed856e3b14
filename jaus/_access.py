"""Who controls the component and in what state it is: JAUS AccessControl and Management
(core service set 1.1, ``AccessControl.xml`` and ``Management.xml``), as pure logic.

The host asks and sends; this module only decides. States, as Management's state machine
names them (``ReportStatus``'s values):

- STANDBY at start, and whenever nobody controls the component;
- READY after Resume from the controlling client (Standby from it goes back);
- EMERGENCY while any Set Emergency is not cleared by the client that set it (then back to
  where it was); nobody takes control meanwhile;
- SHUTDOWN after Shutdown from the controlling client: control is released and never granted
  again (the component is done; ``ups jaus`` exits).

Control is exclusive, and it belongs to a JAUS id *at the transport address* it was asked
from. Request Control is granted when nobody holds it, when the holder asks again, or when the
asker's authority is above the holder's (who then loses it: AS5710A lets a higher authority
take control); never below the component's ``minimum_authority``. The authority asked may be
capped per source address range (:class:`AuthorityCaps`, the mapping's ``[authority]``) before
it gets here. The holder loses control by Release Control, by Reset, by Shutdown, or when it
has sent nothing for ``timeout`` seconds. Commands of the mobility services are accepted only
from the holder and only when READY (:meth:`Access.refusal`).

While an id holds control it is bound to the address it asked from: :meth:`Access.admits`
refuses that id from any other address (the host answers its queries there and takes its Set
Emergency, as anyone's, and drops the rest, counted), so another client using the same id can
neither command, nor keep control alive, nor have the holder's answers sent to it. An
emergency is cleared only by the id *and* address that set it.
"""

from __future__ import annotations

import ipaddress
import logging
import math
import time
from dataclasses import dataclass, field
from enum import IntEnum
from typing import Any

from ._codec import JausId
from ._payloads import ControlResponse

CONTROL_TIMEOUT = 5.0  #: seconds of silence after which the controlling client loses control
MAX_EMERGENCIES = 16  #: clients whose Set Emergency is remembered at once; more are refused
NOTE_EVERY = 10.0  #: seconds between two log lines of one kind of refusal (all are counted)

Address = tuple[Any, ...]  #: a transport address: (host, port) for UDP
Network = ipaddress.IPv4Network | ipaddress.IPv6Network


@dataclass(frozen=True, slots=True)
class AuthorityCaps:
    """The most authority Request Control is granted from each source address range (the
    mapping's ``[authority]`` table). The longest prefix holding the address decides; an
    address in no range is granted no control at all."""

    ranges: tuple[tuple[Network, int], ...]

    def cap(self, host: str) -> tuple[Network, int] | None:
        """The range that holds ``host`` and its cap, or None."""
        ip = _ip(host)
        if ip is None:
            return None
        held = [(net, cap) for net, cap in self.ranges if ip.version == net.version and ip in net]
        return max(held, key=lambda r: r[0].prefixlen, default=None)


def _ip(host: str) -> ipaddress.IPv4Address | ipaddress.IPv6Address | None:
    """The address of a datagram's sender: an IPv4-mapped IPv6 address as IPv4, the scope of a
    link-local one left out."""
    try:
        ip = ipaddress.ip_address(host.partition("%")[0])
    except ValueError:
        return None
    if isinstance(ip, ipaddress.IPv6Address) and ip.ipv4_mapped is not None:
        return ip.ipv4_mapped
    return ip


class Notes:
    """Counts a refusal and logs it, at most once per ``every`` seconds for each counter (a
    flood of them must not flood the log); the line says how many there were so far."""

    def __init__(
        self, counters: dict[str, int], log: logging.Logger, every: float = NOTE_EVERY
    ) -> None:
        self.counters, self.log, self.every = counters, log, every
        self._said: dict[str, float] = {}

    def __call__(self, counter: str, text: str, *args: object) -> None:
        self.counters[counter] = self.counters.get(counter, 0) + 1
        now = time.monotonic()
        if now - self._said.get(counter, -math.inf) >= self.every:
            self._said[counter] = now
            self.log.warning(f"{text} ({counter}: %d so far)", *args, self.counters[counter])


class State(IntEnum):
    """Management's states, numbered as Report Status carries them."""

    INIT = 0
    READY = 1
    STANDBY = 2
    SHUTDOWN = 3
    FAILURE = 4
    EMERGENCY = 5


@dataclass
class Access:
    minimum_authority: int = 0
    timeout: float = CONTROL_TIMEOUT
    holder: JausId | None = None
    holder_address: Address | None = None  #: where the holder asked for control from
    authority: int = 0
    heard: float = 0.0
    state: State = State.STANDBY
    _before_emergency: State = State.STANDBY
    _emergencies: set[tuple[JausId, Address]] = field(default_factory=set)  #: who set one, where

    # --- AccessControl --------------------------------------------------------------------

    def admits(self, who: JausId, address: Address) -> bool:
        """Whether a message from ``who`` at ``address`` may be handled at all: False for the
        holder's id from another address."""
        return who != self.holder or address == self.holder_address

    def request(
        self, who: JausId, authority: int, now: float, address: Address
    ) -> tuple[ControlResponse, JausId | None]:
        """The answer to Request Control from ``who`` at ``address``, and the client that lost
        control to it."""
        self.expire(now)
        if not self.admits(who, address) or self.state in (
            State.EMERGENCY, State.SHUTDOWN, State.FAILURE
        ):  # fmt: skip
            return ControlResponse.NOT_AVAILABLE, None
        if authority < self.minimum_authority:
            return ControlResponse.INSUFFICIENT_AUTHORITY, None
        if self.holder is None or self.holder == who or authority > self.authority:
            displaced = self.holder if self.holder not in (None, who) else None
            if self.holder != who:
                self.state = State.STANDBY  # a new client starts from Standby
            self.holder, self.holder_address = who, address
            self.authority, self.heard = authority, now
            return ControlResponse.CONTROL_ACCEPTED, displaced
        return ControlResponse.NOT_AVAILABLE, None

    def release(self, who: JausId) -> bool:
        """Release Control; True when ``who`` held control."""
        if self.holder != who:
            return False
        self._lose()
        return True

    def heard_from(self, who: JausId, now: float) -> None:
        if who == self.holder:
            self.heard = now

    def expire(self, now: float) -> JausId | None:
        """The holder whose control lapsed just now, if any."""
        if self.holder is not None and now - self.heard > self.timeout:
            lapsed = self.holder
            self._lose()
            return lapsed
        return None

    def controls(self, who: JausId) -> bool:
        return self.holder == who

    def _lose(self) -> None:
        self.holder, self.holder_address, self.authority = None, None, 0
        if self.state == State.READY:
            self.state = State.STANDBY

    # --- Management -----------------------------------------------------------------------

    def resume(self, who: JausId) -> bool:
        if self.controls(who) and self.state == State.STANDBY:
            self.state = State.READY
            return True
        return False

    def standby(self, who: JausId) -> bool:
        if self.controls(who) and self.state == State.READY:
            self.state = State.STANDBY
            return True
        return False

    def reset(self, who: JausId) -> bool:
        """Reset: re-initialised to Standby, control released."""
        if not self.controls(who) or self.state == State.EMERGENCY:
            return False
        self._lose()
        self.state = State.STANDBY
        return True

    def shutdown(self, who: JausId) -> bool:
        if not self.controls(who) or self.state == State.EMERGENCY:
            return False
        self._lose()
        self.state = State.SHUTDOWN
        return True

    def set_emergency(self, who: JausId, address: Address) -> bool:
        """Set Emergency from anyone, anywhere; False when too many clients (an id at an
        address) hold one already."""
        setter = (who, address)
        if setter not in self._emergencies and len(self._emergencies) >= MAX_EMERGENCIES:
            return False
        if self.state != State.EMERGENCY:
            self._before_emergency = self.state
            self.state = State.EMERGENCY
        self._emergencies.add(setter)
        return True

    def clear_emergency(self, who: JausId, address: Address) -> bool:
        """Clear Emergency; only the client that set one clears it, from the address it set
        it from. True when it did."""
        if (who, address) not in self._emergencies:
            return False
        self._emergencies.discard((who, address))
        if not self._emergencies:
            back = self._before_emergency
            self.state = State.STANDBY if back == State.READY and self.holder is None else back
        return True

    def refusal(self, who: JausId) -> str | None:
        """Why a command from ``who`` is not carried out now (a counter's name), or None."""
        if self.state == State.EMERGENCY:
            return "refused_in_emergency"
        if not self.controls(who):
            return "refused_without_control"
        if self.state != State.READY:
            return "refused_not_ready"
        return None


__all__ = [
    "CONTROL_TIMEOUT",
    "MAX_EMERGENCIES",
    "NOTE_EVERY",
    "Access",
    "Address",
    "AuthorityCaps",
    "Notes",
    "State",
]
