# syntax=docker/dockerfile:1
# slc-gateway: Modbus TCP gateway for Allen-Bradley SLC controllers.
#
#   docker build -t slc-gateway .
#   docker run -d --name slc-gateway --device /dev/ttyUSB0 -p 5020:5020 -p 127.0.0.1:9108:9108 \
#       -v "$PWD/config/gateway.toml:/etc/slc-gateway/gateway.toml:ro" \
#       slc-gateway run /etc/slc-gateway/gateway.toml --metrics-listen 0.0.0.0:9108
#
# The image runs `slc-gateway run /etc/slc-gateway/gateway.toml` (config/gateway.toml is built in
# as an example; mount your own over it).  That file keeps the status page and /metrics on
# 127.0.0.1, which inside a container only the container reaches: --metrics-listen 0.0.0.0:9108
# (or [metrics] listen in your own file) lets a published port reach them.  `docker run slc-gateway check-config /etc/...` checks a
# file, `docker run slc-gateway --help` lists the other commands.  See docker-compose.yml.
#
# BASE is any image with Python 3.11 and its venv module (python3 -m venv) and useradd: the
# official python:3.11-slim by default, or a Debian bookworm root filesystem with python3,
# python3-venv and passwd where no registry can be reached (.ci/base-image builds one; CI builds
# this file with `buildah bud --format docker --build-arg BASE=...`, see tests/e2e/test_container_image.py).
ARG BASE=python:3.11-slim

# ---- build: the wheel, from the same files a source checkout has, and a wheelhouse --------------
FROM ${BASE} AS build
ENV PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1
WORKDIR /src
COPY pyproject.toml README.md LICENSE ./
COPY config ./config
COPY gateway ./gateway
# The project's wheel, then the wheels of its pinned dependencies beside it (the only step that
# reaches the package index): the runtime stage installs from /wheels alone, offline.
RUN python3 -m venv /tmp/pip \
 && /tmp/pip/bin/python -m pip wheel --no-deps --wheel-dir /wheels . \
 && /tmp/pip/bin/python -m pip wheel --wheel-dir /wheels /wheels/slc_gateway-*.whl

# ---- runtime ------------------------------------------------------------------------------------
FROM ${BASE}

# The gateway lives in its own virtual environment, first on PATH: `slc-gateway` and `python`
# (the HEALTHCHECK's) are its own, whichever Python the base image has.
ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    PATH=/opt/slc-gateway/bin:$PATH

# The package and its pinned dependencies (pyproject.toml) from the build stage's wheelhouse, with
# no package index: nothing else of the build.
RUN --mount=type=bind,from=build,source=/wheels,target=/wheels \
    python3 -m venv /opt/slc-gateway \
 && /opt/slc-gateway/bin/python -m pip install --no-index --find-links /wheels slc-gateway \
 && /opt/slc-gateway/bin/python -m pip uninstall --yes --quiet pip

# An unprivileged user in the "dialout" group, which owns serial ports on Debian hosts.
RUN useradd --system --uid 10001 --gid dialout --no-create-home --home-dir /nonexistent \
        --shell /usr/sbin/nologin slc-gateway
COPY config/gateway.toml /etc/slc-gateway/gateway.toml
USER slc-gateway:dialout

# 5020 Modbus TCP, 802 Modbus/TCP Security (TLS, when [modbus.tls] is configured),
# 9108 Prometheus /metrics and /healthz (when [metrics] is configured).
EXPOSE 5020 802 9108

# One Modbus read of unit 1's status block (input register 1000) on the Modbus port; answered
# whether or not the controller is up, so it tells that the gateway serves.  Adjust the address
# and unit if your config listens elsewhere (python -m gateway.healthcheck --help).  It connects
# from 127.0.0.1, which [modbus] loopback_reads = true (the default) lets in for reads whatever
# "allow" says.  With TLS only (listen = ""), keep a plain listener on "127.0.0.1:5020" for it.
HEALTHCHECK --interval=30s --timeout=5s --start-period=10s --retries=3 \
    CMD ["python", "-m", "gateway.healthcheck", "127.0.0.1:5020", "1"]

# SIGTERM (docker stop) stops the gateway cleanly: requests in flight finish, links close, exit 0.
# SIGHUP (docker kill -s HUP) re-reads the config file without a restart (docs/guide/reload.md).
STOPSIGNAL SIGTERM
ENTRYPOINT ["slc-gateway"]
CMD ["run", "/etc/slc-gateway/gateway.toml"]
