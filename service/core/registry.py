"""The constitutions the service evaluates, by limit UID: each module registers itself (`register`).

Everything that knows a constitution reads its facts here (`CONSTITUTIONS`): validation, discovery and OpenAPI,
the SDK, the libuipc adapter; the pipeline takes its numerics (`numerics`). The specs' two register when
`jointlimits.service.core` is imported (670, then 669); any module may add another (`register`, `unregister`).
"""

from __future__ import annotations

from jointlimits.service.core.constitution import Constitution, Facts

CONSTITUTIONS: dict[int, Facts] = {}
"""Each served constitution's facts by its limit UID, in the order registered (the order a fault lists them in)."""
_NUMERICS: dict[int, Constitution] = {}


def register(c: Constitution) -> Constitution:
    """Serve `c` under its limit UID from now on, on every path; returns `c`. A UID already served is refused."""
    uid = c.facts.uid
    if uid in CONSTITUTIONS:
        raise ValueError(f"constitution {uid} is already registered ({CONSTITUTIONS[uid].name})")
    CONSTITUTIONS[uid], _NUMERICS[uid] = c.facts, c
    return c


def unregister(uid: int) -> None:
    """Stop serving the constitution `uid` (KeyError if none is registered)."""
    del CONSTITUTIONS[uid], _NUMERICS[uid]


def base_uid_of(uid: int) -> int:
    """The base joint an absent `base_uid` stands for (-1 for an unknown constitution, which validation refuses)."""
    facts = CONSTITUTIONS.get(uid)
    return -1 if facts is None else facts.base_uid


def numerics(uid: int) -> Constitution:
    """The registered constitution `uid` (KeyError if none is: validation refuses it first)."""
    return _NUMERICS[uid]
