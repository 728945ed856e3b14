"""The segment: the EtherCAT master of one interface (pysoem), its slaves brought to OP and the
process data exchanged every cycle on a thread of its own, which nothing on the UPS side can
delay: the outputs it writes are bytes set beforehand (:meth:`Segment.set_output`), the inputs
it reads are handed over without waiting (``on_inputs``, coalesced: the latest wins).

Every cycle checks the working counter. A late cycle, a lost frame (no answer within the cycle)
and a wrong working counter are counted; the slaves' AL states are read after a wrong one and
every ``STATE_CHECK`` s, and a slave out of OP is counted, logged with its AL status code and
brought back (error acknowledged, SAFE-OP, OP; a slave that lost its configuration is set up
again). An output whose channel has been silent for the map's ``timeout`` (or has not spoken
yet) is written with its safe value, by this thread, whatever the UPS side is doing.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import Any

from ._map import EthercatMap, InputChannel, Output
from ._master import EthercatError, al_code_name, open_master, state_name

log = logging.getLogger("ups.ethercat")

INIT, PREOP, SAFEOP, OP, ACK = 1, 2, 4, 8, 0x10
STATE_CHECK = 0.1  #: s between two reads of the slaves' AL states while all is well
START_TIMEOUT_US = 3_000_000  #: how long the slaves may take to reach SAFE-OP, then OP
OP_POLL_US = 2000  #: between two exchanges while the slaves go to OP
LOG_EVERY = 1.0  #: s: the same fault is logged at most this often (counted always)
RECOVER_TIMEOUT_US = 5000  #: how long one step of bringing a slave back may wait
CONFIRM_US = 2000  #: how long a slave found out of OP is asked again before it counts
COUNTERS = (
    "cycles", "late", "lost", "wkc_errors", "left_op", "recoveries", "silent", "coalesced",
)  # fmt: skip


def judge(wkc: int, expected: int) -> str | None:
    """What a cycle's working counter says: None when right, ``"lost"`` when no frame came
    back within the wait (pysoem gives SOEM's EC_NOFRAME, -1), ``"wkc_errors"`` for any other
    count, 0 included (an answer that no slave counted: slaves out of SAFE-OP or OP, or that
    lost their configuration)."""
    if wkc == expected:
        return None
    return "lost" if wkc < 0 else "wkc_errors"


class Segment:
    """The master on ``ifname`` for ``emap``'s slaves, cycling every ``cycle`` s once started.

    ``on_inputs(payloads)`` is called on the thread with {InputChannel: payload} due for
    publishing; it must not block (:class:`EthercatNode` hands them to its event loop)."""

    def __init__(self, ifname: str, emap: EthercatMap, cycle: float | None = None) -> None:
        self.ifname = ifname
        self.map = emap
        self.cycle = cycle or emap.cycle
        self.counts = dict.fromkeys(COUNTERS, 0)
        self.on_inputs: Callable[[dict[InputChannel, bytes]], None] = lambda payloads: None
        #: called on the cycle's thread if the cycle stops on an error (``failure``)
        self.on_failure: Callable[[], None] = lambda: None
        self.failure: Exception | None = None
        self.expected_wkc = 0
        self.last_wkc = 0
        self.states: list[int] = []  #: each slave's AL state as last read
        self._master: Any = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        #: each output's latest raw bytes and when its channel's event came (monotonic s)
        self._latest: dict[Output, tuple[bytes, float]] = {}
        self._live: dict[Any, bool] = {}  # output channel spec -> not silent
        self._changed = True  # an output changed since the images were last made
        self._expires = 0.0  # when the next live output goes silent (monotonic s)
        self._last_raw: dict[int, bytes] = {}  # each input slave's image as last read
        self._input_slaves = sorted({e.slave for c in emap.inputs for e in c.entries})
        self._last_inputs: dict[InputChannel, bytes] = {}
        self._logged: dict[str, float] = {}

    # --- the UPS side ---------------------------------------------------------------------

    def set_output(self, entry: Output, raw: bytes) -> None:
        """``entry``'s bytes from now on (its channel just spoke); any thread."""
        self._latest[entry] = (raw, time.monotonic())
        self._changed = True

    def status(self) -> dict[str, Any]:
        return {
            **self.counts,
            "interface": self.ifname,
            "cycle_ms": round(self.cycle * 1000, 3),
            "expected_wkc": self.expected_wkc,
            "last_wkc": self.last_wkc,
            "slaves": len(self.states),
            "in_op": sum(1 for s in self.states if s == OP),
            "states": [state_name(s) for s in self.states],
        }

    # --- start and stop -------------------------------------------------------------------

    def start(self) -> None:
        """Find the slaves, check them against the map, map the process data, bring them to
        OP and start cycling. Raises EthercatError (and leaves the segment closed)."""
        master = self._master = open_master(self.ifname)
        try:
            self._bring_up(master)
        except BaseException:
            master.close()
            self._master = None
            raise
        self._thread = threading.Thread(target=self._run, name="ups-ethercat", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Stop cycling; the slaves go back to INIT (their outputs safe) and the master closes."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        master, self._master = self._master, None
        if master is None:
            return
        try:
            for slave in master.slaves:
                slave.state = INIT
                slave.write_state()
        except Exception as exc:  # the link may be gone: nothing more to do for the slaves
            log.warning("could not take the slaves to INIT: %s", exc)
        finally:
            master.close()

    def _bring_up(self, master: Any) -> None:
        found = master.config_init()
        if found <= 0:
            raise EthercatError(f"no EtherCAT slave answers on {self.ifname}")
        slaves = master.slaves
        for position, wanted in self.map.slaves.items():
            if position > len(slaves):
                raise EthercatError(
                    f"the map has slave {position} ({wanted.identity()}), the segment on "
                    f"{self.ifname} {len(slaves)} slave(s)"
                )
            slave = slaves[position - 1]
            if (slave.man, slave.id) != (wanted.vendor, wanted.product) or (
                wanted.revision is not None and slave.rev != wanted.revision
            ):
                raise EthercatError(
                    f"slave {position} is vendor 0x{slave.man:08x} product 0x{slave.id:08x} "
                    f"revision 0x{slave.rev:08x}; the map expects {wanted.identity()} "
                    f"(line {wanted.line}): not starting"
                )
        master.config_map()
        for position, wanted in self.map.slaves.items():
            slave = slaves[position - 1]
            for entry in wanted.outputs:
                self._fits(entry.byte + entry.size, len(slave.output), position, entry.line,
                           "output")  # fmt: skip
        for channel in self.map.inputs:
            for e in channel.entries:
                size = len(slaves[e.slave - 1].input)
                self._fits(e.byte + e.size, size, e.slave, e.line, "input")
        self.expected_wkc = master.expected_wkc
        self._write_outputs(time.monotonic())
        master.send_processdata()
        master.receive_processdata(self._timeout_us())
        if master.state_check(SAFEOP, START_TIMEOUT_US) != SAFEOP:
            raise self._behind(master, SAFEOP)
        master.state = OP
        master.write_state()
        deadline = time.monotonic() + START_TIMEOUT_US / 1e6
        while True:  # a slave goes to OP only while valid outputs come: exchange meanwhile
            master.send_processdata()
            master.receive_processdata(self._timeout_us())
            if master.state_check(OP, OP_POLL_US) == OP:
                break
            if time.monotonic() > deadline:
                raise self._behind(master, OP)
        master.read_state()
        self.states = [s.state for s in slaves]

    def _behind(self, master: Any, target: int) -> EthercatError:
        """The error naming each slave that did not reach ``target``, its state and code."""
        master.read_state()
        behind = [
            f"slave {n} in {state_name(s.state)} ({al_code_name(s.al_status)})"
            for n, s in enumerate(master.slaves, 1)
            if s.state != target
        ]
        return EthercatError(f"the slaves did not reach {state_name(target)}: " + "; ".join(behind))

    def _fits(self, end: int, size: int, position: int, line: int, kind: str) -> None:
        if end > size:
            raise EthercatError(
                f"{self.map.path}:{line}: slave {position} has {size} {kind} byte(s); the map "
                f"reaches byte {end - 1}"
            )

    def _timeout_us(self) -> int:
        return max(200, int(self.cycle * 1e6))

    # --- the cycle ------------------------------------------------------------------------

    def _run(self) -> None:
        try:
            self._cycle_until_stopped()
        except Exception as exc:  # a bug, or the interface gone: said, and the node ends
            log.exception("the EtherCAT cycle stopped")
            self.failure = exc
            self.on_failure()

    def _cycle_until_stopped(self) -> None:
        master, period, counts = self._master, self.cycle, self.counts
        master.always_release_gil = True
        timeout = self._timeout_us()
        due = time.monotonic()
        next_check = due + STATE_CHECK
        good = True  # the last cycle's working counter was right
        while not self._stop.is_set():
            now = time.monotonic()
            self._write_outputs(now)
            master.send_processdata()
            wkc = self.last_wkc = master.receive_processdata(timeout)
            counts["cycles"] += 1
            verdict = judge(wkc, self.expected_wkc)
            if verdict is None:
                self._read_inputs()
            else:
                if good:  # the first bad cycle: the states are read at once, then every
                    next_check = now  # STATE_CHECK while it lasts (reading them costs cycles)
                counts[verdict] += 1
                if verdict == "lost":
                    self._say("lost", "EtherCAT frames lost (no answer within the cycle)")
                else:
                    self._say("wkc", f"working counter {wkc}, expected {self.expected_wkc}")
            good = verdict is None
            if now >= next_check:
                self._check_states(master)
                next_check = now + STATE_CHECK
            due += period
            wait = due - time.monotonic()
            if wait > 0:
                time.sleep(wait)
            elif wait < -period / 2:  # this cycle ran past the next one's start: late
                counts["late"] += 1
                due = time.monotonic()  # (the missed exchange is not made up)

    def _write_outputs(self, now: float) -> None:
        """Make the slaves' output images, when an output changed or went silent."""
        if not self._changed and now < self._expires:
            return
        self._changed = False  # (before reading: a change meanwhile makes them again)
        self._expires = float("inf")
        slaves = self._master.slaves
        timeout = self.map.timeout
        for position, wanted in self.map.slaves.items():
            image = bytearray(len(slaves[position - 1].output))
            for entry in wanted.outputs:
                latest = self._latest.get(entry)
                live = latest is not None and now - latest[1] <= timeout
                if live and latest is not None:
                    raw = latest[0]
                    self._expires = min(self._expires, latest[1] + timeout)
                else:
                    raw = entry.safe
                image[entry.byte : entry.byte + entry.size] = raw
                if self._live.get(entry.spec, False) != live:
                    self._live[entry.spec] = live
                    if not live and latest is not None:
                        self.counts["silent"] += 1
                        log.warning("%s silent for %g s: its outputs are safe", entry.spec.channel,
                                    timeout)  # fmt: skip
            slaves[position - 1].output = bytes(image)

    def _read_inputs(self) -> None:
        """Hand the input channels due to ``on_inputs``: those whose bytes changed, those
        published every K cycles at their cycle."""
        slaves = self._master.slaves
        cycles = self.counts["cycles"]
        raw = {position: slaves[position - 1].input for position in self._input_slaves}
        changed = raw != self._last_raw
        if not changed and not any(c.every and cycles % c.every == 0 for c in self.map.inputs):
            return
        self._last_raw = raw
        due: dict[InputChannel, bytes] = {}
        for channel in self.map.inputs:
            if channel.every:
                if cycles % channel.every:
                    continue
            elif not changed:
                continue
            values = {e.field: e.unpack(raw[e.slave]) for e in channel.entries}
            payload = channel.spec.encode(values)
            if channel.every or self._last_inputs.get(channel) != payload:
                self._last_inputs[channel] = payload
                due[channel] = payload
        if due:
            self.on_inputs(due)

    def _check_states(self, master: Any) -> None:
        master.read_state()
        slaves = master.slaves
        before = self.states
        self.states = [s.state for s in slaves]
        for n, slave in enumerate(slaves, 1):
            state = slave.state
            if state != OP:  # ask that slave again: a read lost on a busy link says 0 too
                slave.state_check(OP, CONFIRM_US)  # (it returns the state without the error
                state = self.states[n - 1] = slave.state  # flag; slave.state has it)
            was = before[n - 1] if n - 1 < len(before) else OP
            if state == OP:
                if was != OP:
                    self.counts["recoveries"] += 1
                    log.warning("slave %d is back in OP", n)
                continue
            if was == OP:
                self.counts["left_op"] += 1
            what = (
                "does not answer"
                if state == 0
                else f"is in {state_name(state)} ({al_code_name(slave.al_status)})"
            )  # each new situation said at once, the same one once a second
            self._say(f"{n} {state} {slave.al_status}", f"slave {n} {what}: bringing it back "
                      "to OP")  # fmt: skip
            self._recover(slave, state)

    def _recover(self, slave: Any, state: int) -> None:
        """One step towards OP, as SOEM's examples take it: find a slave that did not answer
        again, acknowledge an error, set up a slave found in INIT or PRE-OP (power cycled or
        replaced) again, ask SAFE-OP for OP. Each step waits at most ``RECOVER_TIMEOUT_US``
        on the cycle's thread (cycles meanwhile are late, and counted)."""
        try:
            if state == 0:
                slave.recover(RECOVER_TIMEOUT_US)
            elif state & ACK:
                slave.state = (state & 0x0F) | ACK
                slave.write_state()
            elif state == SAFEOP:
                slave.state = OP
                slave.write_state()
            elif state in (INIT, PREOP):
                slave.reconfig(RECOVER_TIMEOUT_US)
        except Exception as exc:  # (it may have gone again): tried again at the next check
            self._say("recover", f"recovering a slave failed: {exc}")

    def _say(self, key: str, text: str) -> None:
        now = time.monotonic()
        if now - self._logged.get(key, -LOG_EVERY) >= LOG_EVERY:
            self._logged[key] = now
            log.warning("%s (cycles %d, lost %d, wkc errors %d, late %d)", text,
                        self.counts["cycles"], self.counts["lost"], self.counts["wkc_errors"],
                        self.counts["late"])  # fmt: skip
