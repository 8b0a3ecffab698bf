"""The supported constitutions, by limit UID."""

from __future__ import annotations

from service.core.constitution import Constitution
from service.core.prismatic import PRISMATIC
from service.core.revolute import REVOLUTE

CONSTITUTIONS: dict[int, Constitution] = {c.uid: c for c in (REVOLUTE, PRISMATIC)}
