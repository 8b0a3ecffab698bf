"""`GET /v1/constitutions`: the core's registry, described in the specs' words."""

from __future__ import annotations

from jointlimits.schemas import ConstitutionsResponse, Limits
from jointlimits.schemas.constitutions import describe
from jointlimits.service.core import registry
from jointlimits.service.settings import Settings


def constitutions(settings: Settings) -> ConstitutionsResponse:
    infos = [describe(f) for f in sorted(registry.CONSTITUTIONS.values(), key=lambda f: -f.uid)]
    limits = Limits(
        max_body_bytes=settings.max_body_bytes,
        max_joints=settings.max_joints,
        max_batches=settings.max_batches,
        max_answer_bytes=settings.max_answer_bytes,
        max_json_values=settings.max_json_values,
    )
    return ConstitutionsResponse(constitutions=infos, limits=limits)
