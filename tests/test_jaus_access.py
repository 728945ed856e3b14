"""AccessControl and Management of the JAUS host as a state machine: random sequences of
requests, releases, management commands, emergencies and silence, and what must never happen
(two controllers, a command carried out without control or outside Ready, control taken
during an emergency or after shutdown, a lower authority displacing a higher one)."""

from __future__ import annotations

from hypothesis import settings
from hypothesis import strategies as st
from hypothesis.stateful import RuleBasedStateMachine, invariant, rule

from ups.jaus import ControlResponse, JausId
from ups.jaus._access import MAX_EMERGENCIES, Access, State

CLIENTS = st.sampled_from([JausId(1, 1, 1), JausId(2, 1, 1), JausId(3, 1, 1)])
TIMEOUT = 5.0


class AccessMachine(RuleBasedStateMachine):
    def __init__(self) -> None:
        super().__init__()
        self.access = Access(minimum_authority=10, timeout=TIMEOUT)
        self.now = 0.0
        self.shut = False

    @rule(who=CLIENTS, authority=st.integers(0, 255))
    def request(self, who: JausId, authority: int) -> None:
        before = self.access.holder, self.access.authority, self.access.state
        expired = before[0] is not None and self.now - self.access.heard > TIMEOUT
        response, displaced = self.access.request(who, authority, self.now)
        holder, held_authority, state = before
        if expired:
            holder = None
        if response == ControlResponse.CONTROL_ACCEPTED:
            assert not self.shut and state not in (State.EMERGENCY, State.FAILURE)
            assert authority >= 10
            assert holder in (None, who) or authority > held_authority
            assert displaced == (holder if holder not in (None, who) else None)
            assert self.access.holder == who
        else:
            assert displaced is None
            assert self.access.holder == holder
            if response == ControlResponse.INSUFFICIENT_AUTHORITY:
                assert authority < 10

    @rule(who=CLIENTS)
    def release(self, who: JausId) -> None:
        was = self.access.holder == who
        assert self.access.release(who) == was
        if was:
            assert self.access.holder is None

    @rule(who=CLIENTS)
    def resume(self, who: JausId) -> None:
        state = self.access.state
        if self.access.resume(who):
            assert state == State.STANDBY and self.access.holder == who
            assert self.access.state == State.READY

    @rule(who=CLIENTS)
    def standby(self, who: JausId) -> None:
        if self.access.standby(who):
            assert self.access.state == State.STANDBY

    @rule(who=CLIENTS)
    def reset(self, who: JausId) -> None:
        if self.access.reset(who):
            assert self.access.holder is None and self.access.state == State.STANDBY

    @rule(who=CLIENTS)
    def shutdown(self, who: JausId) -> None:
        if self.access.shutdown(who):
            self.shut = True

    @rule(who=CLIENTS)
    def set_emergency(self, who: JausId) -> None:
        assert self.access.set_emergency(who)
        assert self.access.state == State.EMERGENCY

    @rule(who=CLIENTS)
    def clear_emergency(self, who: JausId) -> None:
        self.access.clear_emergency(who)

    @rule(seconds=st.sampled_from([0.5, 2.0, 4.9, 6.0]))
    def silence(self, seconds: float) -> None:
        self.now += seconds
        holder = self.access.holder
        lapsed = self.access.expire(self.now)
        if lapsed is not None:
            assert lapsed == holder and self.access.holder is None

    @rule(who=CLIENTS)
    def hear(self, who: JausId) -> None:
        self.access.heard_from(who, self.now)

    @invariant()
    def a_command_runs_only_for_the_ready_controller(self) -> None:
        for who in (JausId(1, 1, 1), JausId(2, 1, 1), JausId(3, 1, 1)):
            if self.access.refusal(who) is None:
                assert self.access.holder == who and self.access.state == State.READY

    @invariant()
    def ready_only_under_control(self) -> None:
        if self.access.state == State.READY:
            assert self.access.holder is not None

    @invariant()
    def shutdown_is_final(self) -> None:
        if self.shut:
            assert self.access.state in (State.SHUTDOWN, State.EMERGENCY)
            assert self.access.holder is None


AccessMachine.TestCase.settings = settings(max_examples=150, stateful_step_count=40,
                                           deadline=None)  # fmt: skip
test_access_machine = AccessMachine.TestCase


def test_emergencies_are_bounded_and_cleared_by_their_setters() -> None:
    access = Access()
    assert access.request(JausId(1, 1, 1), 5, 0.0)[0] == ControlResponse.CONTROL_ACCEPTED
    assert access.resume(JausId(1, 1, 1))
    for n in range(MAX_EMERGENCIES):
        assert access.set_emergency(JausId(9, n, 1))
    assert not access.set_emergency(JausId(9, 200, 1))  # the table is full: refused
    assert access.state == State.EMERGENCY
    assert not access.clear_emergency(JausId(1, 1, 1))  # never set one
    for n in range(MAX_EMERGENCIES):
        assert access.clear_emergency(JausId(9, n, 1))
    assert access.state == State.READY  # back where it was, still controlled
    assert access.refusal(JausId(1, 1, 1)) is None
