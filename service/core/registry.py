"""The supported constitutions, by limit UID."""

from __future__ import annotations

from jointlimits.service.core.constitution import Constitution
from jointlimits.service.core.prismatic import PRISMATIC
from jointlimits.service.core.revolute import REVOLUTE

CONSTITUTIONS: dict[int, Constitution] = {c.uid: c for c in (REVOLUTE, PRISMATIC)}
