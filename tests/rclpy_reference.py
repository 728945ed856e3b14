"""Reference bytes and type hashes from real ROS 2: the rclpy, std_msgs and geometry_msgs wheels
of PyPI (ros-jazzy-*), in a virtual environment of their own under .cache/ (their start-up
hook, ros_wheels_bootstrapper, re-executes the interpreter to find their libraries, so they
cannot share the test's).

- payloads: ``rclpy.serialization.serialize_message`` of messages built in rclpy;
- type hashes: the ones ROS 2's build generated into each package's ``share/PKG/msg/T.json``
  (``rosidl_generator_type_description``, compiled into the type support), and for the test's
  own ``.msg`` that same generator run here on it (``rosidl_adapter`` turns it into IDL first).

The environment needs PyPI once (``python -m tests.rclpy_reference`` makes it; scripts/test runs
that before entering the private network namespace, which has no way out); after that the
reference is read from the cache.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
VENV = ROOT / ".cache" / "rclpy-jazzy"
#: exact versions: the reference does not move under the tests
WHEELS = ("ros-jazzy-rclpy[fastrtps]==7.1.6", "ros-jazzy-std-msgs==5.3.6",
          "ros-jazzy-geometry-msgs==5.3.6")  # fmt: skip
MAKE_TIMEOUT = 900.0

#: the test's own message: the fields of geometry_msgs/Vector3Stamped, so rclpy can make its
#: bytes (CDR depends only on the fields' types and order), under a name and hash of its own
CUSTOM_NAME = "ups_test/msg/StampedVector"
CUSTOM_MSG = """\
# A vector with a time stamp and a frame: the test's own message type.
std_msgs/Header header
geometry_msgs/Vector3 vector
"""

#: run in the rclpy environment: prints one JSON object
_SCRIPT = r"""
import json, pathlib, sys, tempfile
from rclpy.serialization import serialize_message
from std_msgs.msg import Float64, Int16, Bool
from geometry_msgs.msg import Twist, Vector3Stamped

share = pathlib.Path(sys.prefix) / "share"
def hash_of(name):
    pkg, _, typ = name.split("/")
    doc = json.loads((share / pkg / "msg" / f"{typ}.json").read_text())
    return next(h["hash_string"] for h in doc["type_hashes"] if h["type_name"] == name)

out = {"payloads": {}, "hashes": {}}
out["payloads"]["std_msgs/msg/Float64"] = serialize_message(Float64(data=-2.75)).hex()
out["payloads"]["std_msgs/msg/Int16"] = serialize_message(Int16(data=-1234)).hex()
out["payloads"]["std_msgs/msg/Bool"] = serialize_message(Bool(data=True)).hex()
t = Twist()
t.linear.x, t.linear.y, t.linear.z = 0.5, -1.25, 3.0
t.angular.x, t.angular.y, t.angular.z = 0.0, 0.125, -0.75
out["payloads"]["geometry_msgs/msg/Twist"] = serialize_message(t).hex()
v = Vector3Stamped()
v.header.stamp.sec, v.header.stamp.nanosec, v.header.frame_id = 1700000000, 250000000, "odom"
v.vector.x, v.vector.y, v.vector.z = 1.0, -2.0, 0.5
out["payloads"]["CUSTOM"] = serialize_message(v).hex()
for name in ("std_msgs/msg/Float64", "std_msgs/msg/Int16", "std_msgs/msg/Bool",
             "geometry_msgs/msg/Twist", "geometry_msgs/msg/Vector3Stamped"):
    out["hashes"][name] = hash_of(name)

from rosidl_adapter.msg import convert_msg_to_idl
from rosidl_generator_type_description import generate_type_hash
pkg_name, msg_type = CUSTOM_NAME.split("/")[0], CUSTOM_NAME.split("/")[2]
with tempfile.TemporaryDirectory() as tmp:
    pkg = pathlib.Path(tmp) / pkg_name
    (pkg / "msg").mkdir(parents=True)
    (pkg / "msg" / f"{msg_type}.msg").write_text(CUSTOM_MSG)
    idl = pathlib.Path(tmp) / "idl"
    convert_msg_to_idl(pkg, pkg_name, pathlib.Path("msg") / f"{msg_type}.msg", idl / "msg")
    args = {"package_name": pkg_name, "output_dir": str(pathlib.Path(tmp) / "out"),
            "idl_tuples": [f"{idl}:msg/{msg_type}.idl"],
            "include_paths": [f"{p}:{share / p}" for p in
                              ("std_msgs", "geometry_msgs", "builtin_interfaces")]}
    (pathlib.Path(tmp) / "args.json").write_text(json.dumps(args))
    for made in generate_type_hash(str(pathlib.Path(tmp) / "args.json")):
        doc = json.loads(pathlib.Path(made).read_text())
        for h in doc["type_hashes"]:
            if h["type_name"] == CUSTOM_NAME:
                out["hashes"][CUSTOM_NAME] = h["hash_string"]
print(json.dumps(out))
"""


def python() -> Path:
    return VENV / "bin" / "python"


def make() -> Path:
    """The rclpy environment, made (from PyPI) if it is not there yet; its Python."""
    stamp = VENV / ".made"
    if stamp.exists() and stamp.read_text() == "\n".join(WHEELS):
        return python()
    subprocess.run([sys.executable, "-m", "venv", "--clear", str(VENV)], check=True)
    subprocess.run(
        [str(python()), "-m", "pip", "install", "-q", "--disable-pip-version-check", *WHEELS],
        check=True, timeout=MAKE_TIMEOUT,
    )  # fmt: skip
    stamp.write_text("\n".join(WHEELS))
    return python()


def reference() -> dict[str, Any]:
    """What real ROS 2 makes: ``payloads`` (hex) and ``hashes``, by type name (the custom
    message's payload under ``CUSTOM``)."""
    cache = VENV / "reference.json"
    code = f"CUSTOM_NAME = {CUSTOM_NAME!r}\nCUSTOM_MSG = {CUSTOM_MSG!r}\n{_SCRIPT}"
    if cache.exists():  # made by this very script (a changed one makes it again)
        cached = json.loads(cache.read_text())
        if cached.get("script") == code:
            return dict(cached["reference"])
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PYTHON", "ROS_", "RMW_"))}
    out = subprocess.run(
        [str(make()), "-c", code], capture_output=True, text=True, check=True, timeout=120,
        env=env, cwd=VENV,
    ).stdout  # fmt: skip
    found: dict[str, Any] = json.loads(out.strip().splitlines()[-1])
    cache.write_text(json.dumps({"script": code, "reference": found}))
    return found


if __name__ == "__main__":  # make the environment and the reference (needs PyPI once)
    print(json.dumps(reference(), indent=2))
