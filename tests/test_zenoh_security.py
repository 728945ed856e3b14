"""Security on the Zenoh face is Zenoh's own: the recipe of docs/zenoh.md (mutual TLS with the
fleet's certificates from ``ups certs``, and an access control list by certificate name), run as
processes exactly as written, and user/password authentication."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import zenoh

from ups import BrokerUnavailable, Node, name_to_uid

from .procs import ROOT, Proc
from .test_zenoh import free_port

RECIPE = ROOT / "examples" / "zenoh"


def certs(folder: Path, *names: str) -> None:
    def ups(*args: str) -> None:
        subprocess.run([sys.executable, "-m", "upscli", "certs", *args], check=True, cwd=folder,
                       capture_output=True)  # fmt: skip

    ups("ca", "pki")
    ups("issue", "pki", "router", "--host", "localhost")
    for name in names:
        ups("issue", "pki", name)


def test_the_readme_recipe_admits_the_fleet_and_no_one_else(tmp_path: Path) -> None:
    for conf in RECIPE.glob("*.json5"):
        shutil.copy(conf, tmp_path)
    certs(tmp_path, "robot", "intruder")
    intruder = (tmp_path / "robot.json5").read_text().replace("pki/robot.", "pki/intruder.")
    (tmp_path / "intruder.json5").write_text(intruder)
    no_cert = json.dumps({"mode": "client", "transport": {"link": {"tls": {
        "root_ca_certificate": "pki/ca.crt"}}}})  # fmt: skip
    (tmp_path / "nocert.json5").write_text(no_cert)
    endpoint = f"tls/localhost:{free_port()}"

    def ups(*args: str, config: str = "robot.json5") -> Proc:
        return Proc(*args, "--zenoh", endpoint, "--zenoh-config", config, cwd=tmp_path)

    router = Proc("zenoh-router", "--listen", endpoint, "--zenoh-config", "router.json5",
                  cwd=tmp_path)  # fmt: skip
    with router:
        router.wait_for_line("Zenoh router .* on")
        with (
            ups("sub", "robot/speed", "--json", "--count", "3", "--timeout", "60") as sub,
            ups("sub", "robot/speed", "--json", "--timeout", "5", config="intruder.json5") as spy,
        ):
            sub.wait_for_line("subscribed to")
            spy.wait_for_line("subscribed to")
            with ups("pub", "robot/speed", "01", "--count", "3", "--rate", "20",
                     "--node-id", "0xF1", config="intruder.json5") as forged:  # fmt: skip
                assert forged.finish(timeout=60)[0] == 0  # its puts go nowhere
            with ups("pub", "robot/speed", "02", "--count", "100", "--rate", "20",
                     "--node-id", "0xF2"):  # fmt: skip
                assert sub.finish(timeout=60)[0] == 0
            events = [json.loads(line) for line in sub.stdout_lines]
            assert {(e["data"], e["source"]) for e in events} == {("02", f"0x{0xF2:016x}")}
            code, out = spy.finish(timeout=60)
            assert code != 0 and out == ""  # the ACL let nothing through to it
        with ups("sub", "robot/speed", "--join-timeout", "2", config="nocert.json5") as stranger:
            code, _ = stranger.finish(timeout=60)
            assert code != 0
            assert "could not join" in "".join(stranger.stderr_lines)


async def test_user_and_password(tmp_path: Path) -> None:
    (tmp_path / "users.txt").write_text("robot:s3cret\n")
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    users = {"usrpwd": {"dictionary_file": str(tmp_path / "users.txt")}}
    router = {
        "mode": "router",
        "listen": {"endpoints": [endpoint]},
        "scouting": {"multicast": {"enabled": False}},
        "transport": {"auth": users},
    }
    (tmp_path / "router.json5").write_text(json.dumps(router))

    def client(password: str) -> Path:
        path = tmp_path / f"client-{password}.json5"
        auth = {"usrpwd": {"user": "robot", "password": password}}
        path.write_text(json.dumps({"transport": {"auth": auth}}))
        return path

    session = zenoh.open(zenoh.Config.from_file(str(tmp_path / "router.json5")))
    try:
        async with Node(zenoh=endpoint, zenoh_config=client("s3cret"), node_id=0xA) as node:
            sub = await node.subscribe(name_to_uid("pw"))
            await node.publish("pw", b"ok")
            assert (await sub.get_msg(timeout=5)).data == b"ok"
        try:
            async with Node(zenoh=endpoint, zenoh_config=client("wrong"), join_timeout=1):
                raise AssertionError("joined with a wrong password")
        except BrokerUnavailable:
            pass
    finally:
        session.close()  # type: ignore[no-untyped-call]
