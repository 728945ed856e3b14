"""AccessControl and Management of the JAUS host as a state machine: random sequences of
requests, releases, management commands, emergencies and silence from clients that are a JAUS
id at an address (two addresses share each id), passed through the host's gate
(``Access.admits``) as the host does, and what must never happen (two controllers, a command
carried out without control, outside Ready or for the controller's id from another address,
control taken during an emergency or after shutdown, a lower authority displacing a higher
one, an emergency cleared from anywhere but where it was set)."""

from __future__ import annotations

from hypothesis import settings
from hypothesis import strategies as st
from hypothesis.stateful import RuleBasedStateMachine, invariant, rule

from ups.jaus import ControlResponse, JausId
from ups.jaus._access import MAX_EMERGENCIES, Access, Address, AuthorityCaps, State

IDS = [JausId(1, 1, 1), JausId(2, 1, 1), JausId(3, 1, 1)]
PLACES: list[Address] = [("10.0.0.1", 3794), ("10.0.0.2", 40000)]
EVERYONE = [(who, at) for who in IDS for at in PLACES]
CLIENTS = st.sampled_from(EVERYONE)
TIMEOUT = 5.0
Client = tuple[JausId, Address]


class AccessMachine(RuleBasedStateMachine):
    def __init__(self) -> None:
        super().__init__()
        self.access = Access(minimum_authority=10, timeout=TIMEOUT)
        self.now = 0.0
        self.shut = False
        self.set: set[Client] = set()  # the emergencies set, by whom and where

    def admitted(self, client: Client) -> bool:
        """The host's gate: the controller's id from another address goes no further."""
        who, at = client
        ok = self.access.admits(who, at)
        assert ok == (who != self.access.holder or at == self.access.holder_address)
        return ok

    @rule(client=CLIENTS, authority=st.integers(0, 255))
    def request(self, client: Client, authority: int) -> None:
        who, at = client
        before = self.access.holder, self.access.holder_address, self.access.authority
        expired = before[0] is not None and self.now - self.access.heard > TIMEOUT
        state = self.access.state
        if not expired and not self.admitted(client):
            return
        response, displaced = self.access.request(who, authority, self.now, at)
        holder, where, held_authority = before
        if expired:
            holder = where = None
        if response == ControlResponse.CONTROL_ACCEPTED:
            assert not self.shut and state not in (State.EMERGENCY, State.FAILURE)
            assert authority >= 10
            assert holder in (None, who) or authority > held_authority
            assert holder != who or where == at  # the same id elsewhere never "asks again"
            assert displaced == (holder if holder not in (None, who) else None)
            assert self.access.holder == who and self.access.holder_address == at
        else:
            assert displaced is None
            assert (self.access.holder, self.access.holder_address) == (holder, where)
            if response == ControlResponse.INSUFFICIENT_AUTHORITY:
                assert authority < 10

    @rule(client=CLIENTS)
    def release(self, client: Client) -> None:
        if self.admitted(client):
            was = self.access.holder == client[0]
            assert self.access.release(client[0]) == was
            if was:
                assert self.access.holder is None and self.access.holder_address is None

    @rule(client=CLIENTS)
    def resume(self, client: Client) -> None:
        state = self.access.state
        if self.admitted(client) and self.access.resume(client[0]):
            assert state == State.STANDBY and self.access.holder == client[0]
            assert self.access.holder_address == client[1]
            assert self.access.state == State.READY

    @rule(client=CLIENTS)
    def standby(self, client: Client) -> None:
        if self.admitted(client) and self.access.standby(client[0]):
            assert self.access.state == State.STANDBY

    @rule(client=CLIENTS)
    def reset(self, client: Client) -> None:
        if self.admitted(client) and self.access.reset(client[0]):
            assert self.access.holder is None and self.access.state == State.STANDBY

    @rule(client=CLIENTS)
    def shutdown(self, client: Client) -> None:
        if self.admitted(client) and self.access.shutdown(client[0]):
            self.shut = True

    @rule(client=CLIENTS)
    def set_emergency(self, client: Client) -> None:
        # past the gate too: anyone may stop the robot (the host hands it on)
        assert self.access.set_emergency(*client)
        assert self.access.state == State.EMERGENCY
        self.set.add(client)

    @rule(client=CLIENTS)
    def clear_emergency(self, client: Client) -> None:
        if self.admitted(client):
            assert self.access.clear_emergency(*client) == (client in self.set)
            self.set.discard(client)
            assert (self.access.state == State.EMERGENCY) == bool(self.set)

    @rule(seconds=st.sampled_from([0.5, 2.0, 4.9, 6.0]))
    def silence(self, seconds: float) -> None:
        self.now += seconds
        holder = self.access.holder
        lapsed = self.access.expire(self.now)
        if lapsed is not None:
            assert lapsed == holder and self.access.holder is None

    @rule(client=CLIENTS)
    def hear(self, client: Client) -> None:
        if self.admitted(client):  # the controller's id from elsewhere keeps nothing alive
            self.access.heard_from(client[0], self.now)

    @invariant()
    def a_command_runs_only_for_the_ready_controller_at_its_address(self) -> None:
        for who, at in EVERYONE:
            if self.access.admits(who, at) and self.access.refusal(who) is None:
                assert self.access.holder == who and self.access.state == State.READY
                assert self.access.holder_address == at

    @invariant()
    def ready_only_under_control(self) -> None:
        if self.access.state == State.READY:
            assert self.access.holder is not None

    @invariant()
    def a_holder_has_an_address(self) -> None:
        assert (self.access.holder is None) == (self.access.holder_address is None)

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
    here, there = ("10.0.0.1", 3794), ("10.0.0.9", 3794)
    assert access.request(JausId(1, 1, 1), 5, 0.0, here)[0] == ControlResponse.CONTROL_ACCEPTED
    assert access.resume(JausId(1, 1, 1))
    for n in range(MAX_EMERGENCIES):
        assert access.set_emergency(JausId(9, n, 1), here)
    assert not access.set_emergency(JausId(9, 200, 1), here)  # the table is full: refused
    assert access.state == State.EMERGENCY
    assert not access.clear_emergency(JausId(1, 1, 1), here)  # never set one
    assert not access.clear_emergency(JausId(9, 0, 1), there)  # its id, from elsewhere
    for n in range(MAX_EMERGENCIES):
        assert access.clear_emergency(JausId(9, n, 1), here)
    assert access.state == State.READY  # back where it was, still controlled
    assert access.refusal(JausId(1, 1, 1)) is None


def test_authority_caps_take_the_longest_prefix_and_know_no_other_address() -> None:
    import ipaddress

    caps = AuthorityCaps(
        (
            (ipaddress.ip_network("10.0.0.0/8"), 50),
            (ipaddress.ip_network("10.1.0.0/16"), 200),
            (ipaddress.ip_network("fd00::/8"), 7),
        )
    )
    assert caps.cap("10.1.2.3") == (ipaddress.ip_network("10.1.0.0/16"), 200)
    assert caps.cap("10.2.2.3") == (ipaddress.ip_network("10.0.0.0/8"), 50)
    assert caps.cap("::ffff:10.2.2.3") == (ipaddress.ip_network("10.0.0.0/8"), 50)  # mapped
    assert caps.cap("fd00::1%eth0") == (ipaddress.ip_network("fd00::/8"), 7)
    assert caps.cap("192.168.1.1") is None and caps.cap("not an address") is None


def test_the_holders_id_from_elsewhere_is_not_the_holder() -> None:
    """Even past the host's gate, Request Control from the holder's id at another address is
    not "the holder asking again" (which would move control there)."""
    access = Access(timeout=TIMEOUT)
    here, there = ("10.0.0.1", 3794), ("10.0.0.1", 40000)
    assert access.request(JausId(1, 1, 1), 5, 0.0, here)[0] == ControlResponse.CONTROL_ACCEPTED
    assert not access.admits(JausId(1, 1, 1), there) and access.admits(JausId(2, 1, 1), there)
    assert access.request(JausId(1, 1, 1), 200, 1.0, there) == (ControlResponse.NOT_AVAILABLE,
                                                                 None)  # fmt: skip
    assert access.holder_address == here
    access.expire(1.0 + TIMEOUT + 0.1)  # the holder fell silent: the id is free again
    assert access.admits(JausId(1, 1, 1), there)
    assert access.request(JausId(1, 1, 1), 5, 7.0, there)[0] == ControlResponse.CONTROL_ACCEPTED
