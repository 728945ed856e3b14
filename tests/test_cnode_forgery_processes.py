"""Forged frames against ``ups c-node`` (libups, the ASan+UBSan build and the minimal one) beside
a real ``ups can-broker``, over udp_multicast in a private network namespace; the forger is a
python-can bus of the test, the publisher ``ups pub`` (issue 41).

Three forged frames: ``Serving(0)`` (the CAN-ECB stands by for a while), ``Bind(the node's etag,
another UID)`` (the node stops relying on its binding and asks again), then, once its request
went, ``Bind(an etag of a size class the node cannot hold, the node's UID)``. Before, libups took
that Bind as the answer and ended the subscription with ``UPS_ERR_TOO_LARGE`` at once, and for
good: ``ups c-node`` exited 1. Now a Bind of a size class the node cannot hold is taken as a
refusal: a channel being bound again keeps asking, and the CAN-ECB's answer, once it serves
again, binds it.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from ups import _canproto as p
from ups import name_to_uid

from .can_wire import wire
from .procs import Proc, private_multicast_bus, sanitizer_env
from .test_cnode_processes import can_broker, events
from .test_tcp_processes import wait_until

pytestmark = pytest.mark.netns

CHANNEL = "robot/brake"
OTHER = name_to_uid("robot/forged")
#: an etag of a size class each build cannot hold: the ASan build takes events up to 1024 bytes
#: (class 3 carries 4096), the minimal one up to 8 (class 1 carries 64)
TOO_LARGE = {"asan": 0x3800, "min": 0x3000}


def c_node_env(build: str) -> dict[str, str]:
    return sanitizer_env() if build == "asan" else {}


@pytest.mark.parametrize("build", ["asan", "min"])
def test_three_forged_frames_leave_a_c_subscriber_bound(tmp_path: Path, build: str) -> None:
    bus = private_multicast_bus()
    uid = name_to_uid(CHANNEL)
    with (
        can_broker(bus, tmp_path / "ecb.db") as ecb,
        wire(bus) as forger,
        Proc("c-node", "--can", bus, "--node-id", "0xc41", "--build", build, "--sub", CHANNEL,
             "--json", env=c_node_env(build)) as node,
    ):  # fmt: skip
        joined = node.wait_for_line("joined as TxNode 0x", timeout=60)
        txnode = int(joined.rsplit("0x", 1)[1], 16)
        bound = node.wait_for_line(f"subscribed: {CHANNEL} is etag 0x", timeout=30)
        etag = int(bound.rsplit("0x", 1)[1], 16)

        def alive() -> None:
            if node.popen.poll() is not None:
                raise AssertionError(f"ups c-node exited {node.popen.returncode}:\n"
                                     + "".join(node.stderr_lines))  # fmt: skip

        forger.send(p.Serving(0))  # the CAN-ECB stands by (it hears the lowest instance serve)
        ecb.wait_for_line("stands by and answers nothing", timeout=10)
        contradicted = forger.send(p.Bind(etag, OTHER))
        asked = p.Request(p.SUB_BIND, txnode, uid)
        wait_until(lambda: asked in forger.heard(contradicted), timeout=10)
        forged = forger.send(p.Bind(TOO_LARGE[build], uid))  # an answer the node cannot hold

        # the CAN-ECB serves again (takes over, says Hello) and answers the node's request
        def answered() -> bool:
            alive()
            return p.Bind(etag, uid) in forger.heard(forged)

        wait_until(answered, timeout=30)
        alive()

        def delivered() -> bool:  # one event through once the node relies on its etag again
            alive()
            with Proc("pub", CHANNEL, "00", "--can", bus, "--node-id", "0x71") as pub:
                assert pub.finish(timeout=20)[0] == 0
            return any(e["data"] == "00" for e in events(node))

        wait_until(delivered, timeout=30)
        with Proc("pub", CHANNEL, "14", "--can", bus, "--count", "20", "--rate", "50",
                  "--node-id", "0x71") as pub:  # fmt: skip
            assert pub.finish(timeout=20)[0] == 0
        wait_until(lambda: [e["data"] for e in events(node)].count("14") == 20, timeout=30)
        alive()
        assert {e["channel"] for e in events(node)} == {CHANNEL}
