"""What a node may register with the TCP-ECB: a channel under its own name only (the name's UID
is the channel's), and, with an ACL, only what the node's identity may do (``_acl``)."""

from __future__ import annotations

from collections.abc import Mapping

from ups import _tcpwire as w
from ups._channel import name_to_uid
from ups._errors import ConfigError

from ._acl import Acl


def refusal(
    identity: str | None,
    frame: w.Subscribe | w.Advertise,
    right: str,
    names: Mapping[int, str],
    acl: Acl | None,
) -> str | None:
    """Why the node of ``identity`` (None without TLS) may not ``right`` (subscribe, publish)
    the channel of ``frame``, whose name may come from ``names`` (uid -> the name registered);
    None: it may."""
    uid = frame.uid
    if frame.name is not None and (theirs := _uid_of(frame.name)) != uid:
        why = "not a channel name" if theirs is None else f"the name of {_hex(theirs)}"
        return f"{frame.name!r:.80} is {why}"
    name = frame.name if frame.name is not None else names.get(uid)
    if acl is not None and not acl.allows(identity, right, uid, name):
        channel = name[:255] if name is not None else _hex(uid)
        return f"identity {identity!r} may not {right} {channel}"
    return None


def _hex(value: int) -> str:
    return f"0x{value:016x}"


def _uid_of(name: str) -> int | None:
    try:
        return name_to_uid(name)
    except ConfigError:
        return None
