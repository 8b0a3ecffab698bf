# syntax=docker/dockerfile:1
# The joint-limit constitution service: `jointlimits serve` on port 8000.
#
#   docker build -t jointlimits .
#   docker run --rm -p 8000:8000 -e JOINTLIMITS_WORKERS=2 jointlimits
#
# tests/ops/test_docker.py keeps this file honest without a Docker engine: it replays the COPY
# and RUN steps of the build stage into a fresh virtual environment, then starts the
# ENTRYPOINT + CMD with the runtime ENV and runs the HEALTHCHECK command against it.

# ---- build: install the package and its runtime dependencies (no test extras) into a venv
FROM python:3.11-slim AS build
ENV VIRTUAL_ENV=/opt/venv \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    PIP_NO_CACHE_DIR=1
WORKDIR /src
COPY pyproject.toml README.md ./
COPY service ./service
COPY schemas ./schemas
COPY client ./client
COPY jointlimits ./jointlimits
RUN python -m venv "$VIRTUAL_ENV" && "$VIRTUAL_ENV/bin/pip" install --no-compile . && "$VIRTUAL_ENV/bin/python" -m compileall -q -j 0 "$VIRTUAL_ENV/lib"

# ---- runtime: the venv only, as an unprivileged user
FROM python:3.11-slim
COPY --from=build /opt/venv /opt/venv
RUN useradd --system --uid 10001 --no-create-home --shell /usr/sbin/nologin jointlimits
ENV VIRTUAL_ENV=/opt/venv \
    PATH=/opt/venv/bin:$PATH \
    PYTHONUNBUFFERED=1 \
    PYTHONDONTWRITEBYTECODE=1 \
    OPENBLAS_NUM_THREADS=1 \
    OMP_NUM_THREADS=1 \
    MKL_NUM_THREADS=1 \
    JOINTLIMITS_HOST=0.0.0.0 \
    JOINTLIMITS_PORT=8000 \
    JOINTLIMITS_WORKERS=auto \
    JOINTLIMITS_GRACEFUL_TIMEOUT=30
USER 10001:10001
WORKDIR /tmp
EXPOSE 8000
# No curl in the slim image: the venv's Python asks /healthz on the configured port.
HEALTHCHECK --interval=15s --timeout=3s --start-period=20s --retries=3 \
    CMD ["python", "-c", "import os, urllib.request; urllib.request.urlopen('http://127.0.0.1:%s/healthz' % os.environ.get('JOINTLIMITS_PORT', '8000'), timeout=2)"]
# Exec form: jointlimits is PID 1 and gets `docker stop`'s SIGTERM itself (graceful shutdown).
ENTRYPOINT ["jointlimits"]
CMD ["serve"]
