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

Control is exclusive. Request Control is granted when nobody holds it, when the holder asks
again, or when the asker's authority is above the holder's (who then loses it); never below
the component's ``minimum_authority``. The holder loses it by Release Control, by Reset, by
Shutdown, or when it has sent nothing for ``timeout`` seconds. Commands of the mobility
services are accepted only from the holder and only when READY (:meth:`Access.refusal`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import IntEnum

from ._codec import JausId
from ._payloads import ControlResponse

CONTROL_TIMEOUT = 5.0  #: seconds of silence after which the controlling client loses control
MAX_EMERGENCIES = 16  #: clients whose Set Emergency is remembered at once; more are refused


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
    authority: int = 0
    heard: float = 0.0
    state: State = State.STANDBY
    _before_emergency: State = State.STANDBY
    _emergencies: set[JausId] = field(default_factory=set)

    # --- AccessControl --------------------------------------------------------------------

    def request(
        self, who: JausId, authority: int, now: float
    ) -> tuple[ControlResponse, JausId | None]:
        """The answer to Request Control, and the client that lost control to ``who``."""
        self.expire(now)
        if self.state in (State.EMERGENCY, State.SHUTDOWN, State.FAILURE):
            return ControlResponse.NOT_AVAILABLE, None
        if authority < self.minimum_authority:
            return ControlResponse.INSUFFICIENT_AUTHORITY, None
        if self.holder is None or self.holder == who or authority > self.authority:
            displaced = self.holder if self.holder not in (None, who) else None
            if self.holder != who:
                self.state = State.STANDBY  # a new client starts from Standby
            self.holder, self.authority, self.heard = who, authority, now
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
        self.holder, self.authority = None, 0
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

    def set_emergency(self, who: JausId) -> bool:
        """Set Emergency from anyone; False when too many clients hold one already."""
        if who not in self._emergencies and len(self._emergencies) >= MAX_EMERGENCIES:
            return False
        if self.state != State.EMERGENCY:
            self._before_emergency = self.state
            self.state = State.EMERGENCY
        self._emergencies.add(who)
        return True

    def clear_emergency(self, who: JausId) -> bool:
        """Clear Emergency; only the client that set one clears it. True when it did."""
        if who not in self._emergencies:
            return False
        self._emergencies.discard(who)
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


__all__ = ["CONTROL_TIMEOUT", "MAX_EMERGENCIES", "Access", "State"]
