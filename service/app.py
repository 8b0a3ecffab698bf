"""The ASGI application `service.app:app`."""

from __future__ import annotations

from fastapi import FastAPI

from service.core import InputError
from service.http.errors import input_error_handler
from service.http.routes import router
from service.settings import Settings


def create_app(settings: Settings | None = None) -> FastAPI:
    settings = settings or Settings()
    app = FastAPI(
        title="Joint-limit constitution service",
        version="1.0.0",
        description="Energy, gradient and Hessian of #670 AffineBodyRevoluteJointLimit "
        "and #669 AffineBodyPrismaticJointLimit (wire contract v1).",
    )
    app.state.settings = settings
    app.include_router(router)
    app.add_exception_handler(InputError, input_error_handler)
    return app


app = create_app()
