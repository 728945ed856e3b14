"""The binding quota: how many bindings each node id may create (docs/protocol.md, Bounds).

A node *creates* a binding when its request (SUB_BIND, PUB_BIND) or its report (SUB_AT,
PUB_AT) makes the CAN-ECB bind a UID that had no etag, or move a channel to a larger size class.
A request names a TxNode; it is charged to the node id that holds that TxNode, so a TxNode's
quota is its holder's, and a TxNode nobody holds creates nothing (its requests are ignored).
The binding counts against that node id, in its size class, for as long as it is bound: until
the lease reclaims its etag (or the channel moves on). Using a channel that is bound already
costs nothing, however many nodes use it. The creator is stored with the binding (the store's
``creators``), so neither a restart of the CAN-ECB nor joining again gives an id a fresh quota.

``QUOTA``: 1024 bindings of size class 0 (of 12 272) and 64 of each class 1-4 (of 1024) per
node id, 1/12 and 1/16 of each class. A node that uses hundreds of channels creates at most as
many (fewer when others bound them first), so it never meets the quota; two rogue ids take at
most 2048 and 128 of them, and it takes 12 ids, each holding a TxNode, to use up class 0.
"""

from __future__ import annotations

from collections import Counter, defaultdict
from collections.abc import Mapping

from ups import _cantransfer as sizes

#: bindings one node id may create and hold, per size class (0 .. 4)
QUOTA = (1024, 64, 64, 64, 64)


class Quota:
    """The bindings each node id created. ``creators`` (uid -> node id) is the store's table,
    kept here as bindings are made and reclaimed; ``etag_of`` (uid -> etag) the store's etags.
    A creation waiting for its write is ``reserve``d, then ``commit``ted (or ``cancel``led)."""

    def __init__(
        self, limits: tuple[int, ...], creators: dict[int, int], etag_of: Mapping[int, int]
    ) -> None:
        self.limits = limits
        self.creators = creators
        #: (node id, size class) -> the UIDs it created there (stored)
        self._made: defaultdict[tuple[int, int], set[int]] = defaultdict(set)
        self._class: dict[int, int] = {}  # uid -> its binding's size class, for each creator
        for uid, node_id in list(creators.items()):
            if uid in etag_of:
                self._class[uid] = size_class = sizes.size_class(etag_of[uid])
                self._made[node_id, size_class].add(uid)
            else:  # a row left over (its binding is gone): it counts against nobody
                del creators[uid]
        self._reserved: dict[int, tuple[int, int]] = {}  # uid -> (node id, class) being stored
        self._reserving: Counter[tuple[int, int]] = Counter()

    def allows(self, node_id: int, size_class: int) -> bool:
        """May ``node_id`` create one more binding of ``size_class``?"""
        return self.used(node_id, size_class) < self.limits[size_class]

    def used(self, node_id: int, size_class: int) -> int:
        """The bindings of ``size_class`` that ``node_id`` created, or is creating."""
        key = (node_id, size_class)
        return len(self._made.get(key, ())) + self._reserving[key]

    def reserve(self, uid: int, node_id: int, size_class: int) -> None:
        """``node_id`` creates a binding of ``uid`` in ``size_class``; it is being stored."""
        self.cancel(uid)
        self._reserved[uid] = (node_id, size_class)
        self._reserving[node_id, size_class] += 1

    def commit(self, uid: int) -> None:
        """The binding reserved for ``uid`` is stored: it replaces the one ``uid`` had."""
        reserved = self._reserved.get(uid)
        if reserved is not None:
            self.cancel(uid)
            self.adopt(uid, *reserved)

    def cancel(self, uid: int) -> None:
        """The binding reserved for ``uid`` is not made (its write failed)."""
        reserved = self._reserved.pop(uid, None)
        if reserved is not None:
            self._reserving[reserved] -= 1
            if self._reserving[reserved] <= 0:
                del self._reserving[reserved]

    def adopt(self, uid: int, node_id: int, size_class: int) -> None:
        """``uid``'s binding, of ``size_class``, is now the creation of ``node_id``."""
        self.release(uid)
        self.creators[uid] = node_id
        self._class[uid] = size_class
        self._made[node_id, size_class].add(uid)

    def release(self, uid: int) -> None:
        """``uid`` is bound no more (reclaimed), or bound anew: it counts against nobody."""
        node_id = self.creators.pop(uid, None)
        size_class = self._class.pop(uid, None)
        if node_id is None or size_class is None:
            return
        made = self._made[node_id, size_class]
        made.discard(uid)
        if not made:
            del self._made[node_id, size_class]

    def created_by(self, node_id: int, size_class: int) -> set[int]:
        """The UIDs ``node_id`` created in ``size_class`` (stored ones)."""
        return set(self._made.get((node_id, size_class), ()))
