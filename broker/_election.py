"""Which CAN-ECB serves a bus: the election between CAN-ECBs, as a pure state machine.

No I/O and no clock. The caller passes the time (seconds on any monotonic clock), hands over
every CAN-ECB frame it hears that it did not send (``heard``), calls ``tick`` when
``deadline`` has come, and sends the frames each call returns. ``CanEcb`` drives it on a
bus; ``tests/test_ecb_election.py`` drives the same code on a simulated one.

The rules (docs/protocol.md, "More than one CAN-ECB"), in short. A CAN-ECB is a *candidate*
from its Hello until its candidacy ends (its recovery window, at most ``MAX_CANDIDACY``), then
it *serves*, and says so with Serving. Claims are ranked by one order that every CAN-ECB
applies alike: a Serving outranks a Hello, and of two of a kind the lower instance wins. So a
candidate stands by on any Serving and on the Hello of a lower instance; a serving CAN-ECB
stands by only on the Serving of a lower instance, and answers every other CAN-ECB frame
(a Hello, a Probe, anything else) with its Serving. A CAN-ECB that stands by sends Probe, which
ranks nowhere: it asks, and a serving CAN-ECB answers, but it never makes anyone stand by or
keeps anyone standing by. Only a Hello or a Serving of another instance keeps a standing-by
CAN-ECB standing by; after ``TAKEOVER`` without one, it says Hello and becomes a candidate.

Why standing by is stable: a serving CAN-ECB answers each Probe within ``SERVING_GAP`` (plus
the bus's delay), and a standing-by one probes every ``PROBE`` s, so it hears a Serving at
least every ``PROBE + SERVING_GAP`` s (< ``TAKEOVER``) for as long as one serves; a candidate
has said Hello and says Serving when its candidacy ends (``MAX_CANDIDACY`` < ``TAKEOVER``).
Why the first to serve stays: a newcomer hears the answer to its Hello while it is a candidate,
unless its candidacy is shorter than that answer's wait (at most ``SERVING_GAP``, and none
when the serving one has answered nothing in the last second).
Why two never stay serving: each sends a Serving at least every ``BEAT`` s, and the higher
instance stands by on hearing the lower one's.

A Serving is only a claim, and anyone can send one. So a standing-by CAN-ECB also watches the
requests it hears (``asked``: a Knock; a SUB_BIND or PUB_BIND of a UID from a TxNode that is
*held*: in its own table, given by an Assign it heard from another, or claimed within
``MAX_CANDIDACY`` s of a Hello, as in a recovery) for their answers (a
census frame; a Bind, EtagsFull, Failed or Limit of that UID; one heard up to ``EARLY`` s
before the request counts: frames of two senders may cross), and when one has had none for
``ANSWER`` s it takes over, whatever Servings say. ``ANSWER`` is longer than the 2 s a serving
CAN-ECB may hold a request (its recovery), and short enough that the request's node, which asks
for 5 s, has its answer after the takeover's own recovery: ``ANSWER`` + 2 s. A binding
request of a TxNode that is not held is not watched: the one that serves owes it no answer
(a request from a TxNode no node holds is ignored), so a forger's, now and then, would make the
CAN-ECBs swap roles on and on, each swap a recovery window for the bus.

From then on it is *wary*, for the rest of its run: as a candidate it stands by for nothing,
and serving it stands by for a lower Serving only with an answer it did not send heard within
``BACKING`` s of it (another CAN-ECB that serves answers what it answers), and not while it is
busy (a census, a recovery); a lower Serving without that it does not answer. So claims alone
silence a CAN-ECB once per run. Two wary CAN-ECBs that both serve (after lost frames) stay so
until they both answer a request; then the higher instance stands by.
"""

from __future__ import annotations

import enum
import math

from ups import _canproto as p
from ups._canproto import Hello, Management, Probe, Serving

SERVING_GAP = 1.0  #: at most one Serving in answer per this many seconds (one due sooner waits)
PROBE = 2.0  #: a standing-by CAN-ECB sends Probe this often
TAKEOVER = 4.0  #: ... and takes over after this long without a Hello or Serving of another
BEAT = 10.0  #: a serving CAN-ECB sends Serving at least this often, asked or not
MAX_CANDIDACY = 2.0  #: a candidate serves (and says Serving) at most this long after its Hello
ANSWER = 2.5  #: a standing-by CAN-ECB takes over when a request it heard had no answer this long
BACKING = 2.0  #: a wary CAN-ECB stands by only with another's answer this close to the Serving
WATCHED = 1024  #: requests a standing-by CAN-ECB watches at once (more are not watched)
EARLY = 1.0  #: an answer heard up to this long before its request counts (frames may cross)
KNOCK = -1  #: the key of joiners' Knocks among the watched requests (the others' are UIDs)

Frame = Hello | Serving | Probe


class Role(enum.Enum):
    STOPPED = "stopped"  #: not started
    CANDIDATE = "candidate"  #: said Hello; stands by on any Serving or a lower Hello
    SERVING = "serving"  #: stands by only on the Serving of a lower instance
    STANDBY = "standby"  #: another CAN-ECB serves; Probe now and then


class Election:
    """The election state of CAN-ECB ``instance``, whose recovery window lasts ``recovery``
    seconds (its candidacy lasts as long, at most ``MAX_CANDIDACY``)."""

    def __init__(self, instance: int, recovery: float = MAX_CANDIDACY) -> None:
        self.instance = instance
        self.candidacy = min(max(recovery, 0.0), MAX_CANDIDACY)
        self.role = Role.STOPPED
        self.reason = ""  #: why it stands by, or why it took over
        self._until = math.inf  # candidate: when the candidacy ends
        self._heard = -math.inf  # standing by: the last Hello or Serving of another
        self._next_probe = math.inf
        self._last_serving = -math.inf  # any Serving (the beat counts from it)
        self._last_answer = -math.inf  # a Serving in answer to another's frame
        self._due: float | None = None  # a Serving owed, to be sent at this time
        self.wary = False  #: it caught another not answering: claims alone move it no more
        self.unanswered = 0  #: takeovers because a request it heard had no answer
        #: standing by: the requests heard and not answered yet (KNOCK, or a UID) -> since when,
        #: oldest first
        self._asked: dict[int, float] = {}
        self._answer = -math.inf  # the last answer to a node that another sent
        self._answered: dict[int, float] = {}  # request key -> when an answer to it was heard
        self._lower = -math.inf  # serving, wary: the last Serving of a lower instance
        #: the TxNodes of the Assigns of others, and of the CLAIMs that answered a Hello, heard
        #: since its own last Hello (at most 127)
        self._assigned: set[int] = set()
        self._hello = -math.inf  # the last Hello, its own or another's

    @property
    def active(self) -> bool:
        """A candidate or serving: it answers nodes (a candidate as in recovery)."""
        return self.role in (Role.CANDIDATE, Role.SERVING)

    @property
    def deadline(self) -> float | None:
        """When ``tick`` must be called next (None: not before the next frame)."""
        if self.role is Role.CANDIDATE:
            return self._until
        if self.role is Role.SERVING:
            beat = self._last_serving + BEAT
            return beat if self._due is None else min(self._due, beat)
        if self.role is Role.STANDBY:
            due = min(self._heard + TAKEOVER, self._next_probe)
            return min(due, next(iter(self._asked.values())) + ANSWER) if self._asked else due
        return None

    def start(self, now: float) -> list[Frame]:
        """The CAN-ECB starts: Hello, and a candidacy."""
        return self._candidate(now)

    def asked(self, msg: Management, now: float, held: bool = False) -> list[Frame]:
        """A node's frame heard while this CAN-ECB stands by: a request that the one serving
        must answer is watched until its answer comes (``tick`` takes over ``ANSWER`` s after
        it if none has). ``held``: this CAN-ECB's own table holds the frame's TxNode; a
        binding request is watched only from a TxNode so held, given by an Assign heard, or
        claimed within ``MAX_CANDIDACY`` of a Hello."""
        key = _request(msg)
        watched = self._asked
        if self.role is not Role.STANDBY:
            return []
        if (
            isinstance(msg, p.Request)
            and msg.kind == p.CLAIM
            and now - self._hello <= MAX_CANDIDACY
        ):
            self._assigned.add(msg.txnode)  # it answers a Hello: a recovery adopts it
        if key is None or len(watched) >= WATCHED:
            return []
        if isinstance(msg, p.Request) and not held and msg.txnode not in self._assigned:
            return []  # nobody holds it, as far as it knows: the one serving owes no answer
        if now - self._answered.get(key, -math.inf) > EARLY:  # its answer may come first
            watched.setdefault(key, now)  # since when it is asked: its first time
        return []

    def heard(self, msg: Management, now: float, busy: bool = False) -> list[Frame]:
        """A CAN-ECB frame that this one did not send (any kind, also Bind, Assign, ...);
        ``busy``: this one has work under way that standing by would drop (a census, a
        recovery)."""
        other = msg.instance if isinstance(msg, Hello | Serving | Probe) else None
        if other == self.instance:  # its own instance: an echo or a forger, not a rival
            return []
        if isinstance(msg, Hello):
            self._hello = now  # the nodes claim: the CLAIMs that follow are held
        if other is None:  # an answer to a node (another CAN-ECB's, or a forger's)
            self._answer = now
            if isinstance(msg, p.Assign):
                self._assigned.add(msg.txnode)  # its binding requests are owed answers
            answered = self._answered  # oldest first
            for key in _answers(msg):
                self._asked.pop(key, None)
                answered.pop(key, None)
                answered[key] = now
            while answered and (
                len(answered) > WATCHED or next(iter(answered.values())) < now - EARLY
            ):
                del answered[next(iter(answered))]
        if self.role is Role.STANDBY:
            if isinstance(msg, Hello | Serving):
                self._heard = now  # one serves, or is about to
            return []
        if self.role is Role.CANDIDATE and self.wary:
            return []  # it serves its candidacy out: what it holds is answered then
        if self.role is Role.CANDIDATE:
            if isinstance(msg, Serving):
                return self._stand_by(now, f"CAN-ECB {msg.instance:016x} already serves this bus")
            if isinstance(msg, Hello) and msg.instance < self.instance:
                return self._stand_by(
                    now, f"CAN-ECB {msg.instance:016x} started as well, with a lower instance"
                )
            return []  # a higher Hello stands by on ours; a Probe asks the one that serves
        if self.role is Role.SERVING:
            lower = isinstance(msg, Serving) and msg.instance < self.instance
            if lower and not self.wary:
                return self._stand_by(
                    now, f"CAN-ECB {other:016x} serves this bus too, with a lower instance"
                )
            if lower:
                self._lower = now
            if self.wary and not busy and self._backed(now):
                return self._stand_by(now, "a CAN-ECB of a lower instance serves this bus too, "
                                      "and answers what this one answers")  # fmt: skip
            if lower:  # a claim with no answers behind it yet; a Serving would tell its sender
                return []  # nothing (it does not stand by for a higher one)
            return self._serve(now)  # whoever sends CAN-ECB frames: this one serves
        return []

    def tick(self, now: float) -> list[Frame]:
        """Timers: the candidacy's end, a Serving owed or due, a Probe, a takeover."""
        if self.role is Role.CANDIDATE and now >= self._until:
            self.role = Role.SERVING
            return self._announce(now)  # standing-by CAN-ECBs hear that one serves
        if self.role is Role.SERVING:
            if self._due is not None and now >= self._due:
                return self._serve(now)
            if now >= self._last_serving + BEAT:
                return self._announce(now)
        elif self.role is Role.STANDBY:
            if self._asked and now >= next(iter(self._asked.values())) + ANSWER:
                self.wary = True  # a claim without answers: a forger's, or a broken CAN-ECB's
                self.unanswered += 1
                self.reason = f"a request had no answer for {ANSWER:g} s"
                return self._candidate(now)
            if now >= self._heard + TAKEOVER:
                self.reason = f"no other CAN-ECB said Serving for {TAKEOVER:g} s"
                return self._candidate(now)
            if now >= self._next_probe:
                self._next_probe = now + PROBE
                return [Probe(self.instance)]
        return []

    def _backed(self, now: float) -> bool:
        """Wary: a lower Serving and an answer it did not send, both lately."""
        return now - self._lower <= BACKING and now - self._answer <= BACKING

    def _candidate(self, now: float) -> list[Frame]:
        self._asked.clear()
        self._assigned.clear()  # its recovery learns the TxNodes in use (their claims)
        self._hello = now
        self.role = Role.CANDIDATE
        self._until = now + self.candidacy
        return [Hello(self.instance)]

    def _stand_by(self, now: float, reason: str) -> list[Frame]:
        self.role = Role.STANDBY
        self.reason = reason
        self._asked.clear()
        self._heard = now
        self._next_probe = now + PROBE
        self._due = None
        return []

    def _serve(self, now: float) -> list[Frame]:
        """Serving in answer: now, or (within ``SERVING_GAP`` of the last answer) once the gap
        has passed. The Serving that ends a candidacy and the beat answer nobody: they do not
        count, so that a newcomer's Hello just after them is answered at once."""
        if now >= self._last_answer + SERVING_GAP:  # (as ``deadline`` adds them)
            self._last_answer = now
            self._due = None
            return self._announce(now)
        self._due = self._last_answer + SERVING_GAP
        return []

    def _announce(self, now: float) -> list[Frame]:
        self._last_serving = now
        return [Serving(self.instance)]


def _request(msg: Management) -> int | None:
    """The key of a request that a serving CAN-ECB answers (None: not one)."""
    if isinstance(msg, p.Knock):
        return KNOCK
    if isinstance(msg, p.Request) and msg.kind in (p.SUB_BIND, p.PUB_BIND):
        return msg.value
    return None


def _answers(msg: Management) -> tuple[int, ...]:
    """The keys of the requests that a CAN-ECB frame answers."""
    if isinstance(msg, p.Census | p.Query | p.Offer | p.Assign | p.TxNodesFull):
        return (KNOCK,)
    if isinstance(msg, p.Failed):  # of a node id (a join) or of a UID
        return (KNOCK, msg.value)
    if isinstance(msg, p.Bind | p.EtagsFull | p.Limit):
        return (msg.uid,)
    return ()
