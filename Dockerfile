# hmcc-match: one image for the API (`hmcc serve`, the default) and the RQ workers
# (`hmcc worker`). docker-compose.yml runs both; tests/service/test_compose.py checks this file.
#
# Two stages: the build stage pip-installs the project (runtime dependencies only, no extras)
# into a virtualenv; the runtime stage copies just that virtualenv, so no source tree, pip cache
# or build backend ends up in the image.
#
# No apt packages: the manylinux wheels of opencv-python-headless, numpy, scipy and numba
# (llvmlite) bundle their libraries and link only against libc, libm, libstdc++, libgcc_s and
# zlib, which the slim image already has (checked with ldd on cv2, llvmlite and the bundled
# .libs; headless needs neither libGL nor libglib).

ARG PYTHON_IMAGE=python:3.11-slim

FROM ${PYTHON_IMAGE} AS build
ENV PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1
RUN python -m venv /opt/venv
WORKDIR /src
# setuptools reads README.md (the project's readme) when it builds the package.
COPY pyproject.toml README.md ./
# The client (hmcc_client) is its own distribution in client/, which the service imports
# (`hmcc colmap --url`, `hmcc flight --url`). The service's pyproject does not name it, so
# it is installed from its path, in the same pip run: no index is asked for `hmcc-client`.
COPY client/ client/
COPY worker/ worker/
COPY service/ service/
RUN /opt/venv/bin/pip install ./client .
# Compile the core's numba loops into a cache the runtime stage reuses (about 40 s here, so
# containers start warm). numba only uses a cache directory it can write to, hence the chown
# below; on a host with another CPU it recompiles into the same directory once.
ENV NUMBA_CACHE_DIR=/opt/numba-cache
RUN /opt/venv/bin/python -c "from hmcc_worker.warm import warm_up; warm_up()"

FROM ${PYTHON_IMAGE}
ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    NUMBA_CACHE_DIR=/opt/numba-cache \
    PATH=/opt/venv/bin:$PATH
# A fixed numeric uid, so orchestrators can check runAsNonRoot. The virtualenv stays owned by
# root: the service cannot modify its own code.
RUN groupadd --system --gid 10001 hmcc \
    && useradd --system --uid 10001 --gid hmcc --no-create-home --home-dir /nonexistent \
        --shell /usr/sbin/nologin hmcc
COPY --from=build /opt/venv /opt/venv
COPY --from=build --chown=10001:10001 /opt/numba-cache /opt/numba-cache
USER 10001:10001
EXPOSE 8000
# Liveness of the API process (not of Redis or the workers: /readyz says that). No curl in
# slim, so python's urllib; any error or non-2xx answer raises and exits 1. The port is
# HMCC_PORT when set (a `hmcc serve` without --port uses it), else the default 8000.
# Worker containers override this check (docker-compose.yml).
HEALTHCHECK --interval=15s --timeout=5s --start-period=30s --retries=3 \
    CMD ["python", "-c", "import os, urllib.request; urllib.request.urlopen('http://127.0.0.1:' + os.environ.get('HMCC_PORT', '8000') + '/healthz', timeout=3)"]
CMD ["hmcc", "serve", "--host", "0.0.0.0", "--port", "8000"]
