# One image for every role: snail-garbler, snail-evaluator, snail-mapd, snail-client (and
# snail-bench). BASE is any Debian-like image with Python >= 3.10 and venv:
#   docker build .                                      (python:3.11-slim from a registry)
#   deploy/build-base && docker build --build-arg BASE=snail-base:bookworm .
#                                                       (no registry: Debian packages only)
# The project and its dependencies go into a venv (PEP 668) in a build stage, with the
# native garbling kernel compiled there (gcc from the base's apt); the final stage copies
# only the venv and the kernel's folder: no compiler, no pip or apt caches, no sources.
# The daemons load that library (its recorded hashes checked) and say "native" on their
# start-up line and /health; where it cannot run they serve numpy and say why.
# Offline: deploy/wheelhouse fills deploy/wheels/ and pip then installs only from there.
ARG BASE=python:3.11-slim

FROM ${BASE} AS build
# lets deploy/compose-test remove this stage's leftover image (the classic builder keeps it)
LABEL org.snail.stage=build
COPY deploy/wheels/ /wheels/
COPY pyproject.toml README.md /src/
COPY snail_common /src/snail_common
COPY snail_client /src/snail_client
COPY snail_garbler /src/snail_garbler
COPY snail_evaluator /src/snail_evaluator
COPY snail_mapd /src/snail_mapd
COPY snail_bench /src/snail_bench
RUN command -v cc >/dev/null || { apt-get update \
      && apt-get install -y --no-install-recommends gcc libc6-dev \
      && rm -rf /var/lib/apt/lists/*; }
RUN set -e; python3 -m venv /opt/snail; \
    if ls /wheels/*.whl >/dev/null 2>&1; then \
        echo "installing from deploy/wheels only"; from="--no-index --find-links /wheels"; \
    else from=""; fi; \
    /opt/snail/bin/pip install --no-cache-dir --disable-pip-version-check $from /src; \
    /opt/snail/bin/python -m pip uninstall --yes --quiet pip setuptools
# the kernel, built for the runtime user (the folder must be its own, mode 0700)
RUN SNAIL_KERNEL_DIR=/opt/snail-kernel /opt/snail/bin/python -c \
      "from snail_common.gc.native.build import build_and_load; print(build_and_load()[1])"

FROM ${BASE}
# tc (netem lab) is in iproute2: Debian's base has it, the official slim image does not
RUN command -v tc >/dev/null || { apt-get update \
      && apt-get install -y --no-install-recommends iproute2 \
      && rm -rf /var/lib/apt/lists/*; }
# an unprivileged user; the volume mount points belong to it, so fresh volumes do too
RUN useradd --system --uid 10001 --user-group --no-create-home --home-dir /nonexistent \
        --shell /usr/sbin/nologin snail \
 && mkdir -p /cache /tls /ca /out/garbler /out/evaluator /out/client \
 && chown snail:snail /cache /tls /ca /out/garbler /out/evaluator /out/client
COPY --from=build /opt/snail /opt/snail
COPY --from=build --chown=10001:10001 /opt/snail-kernel /opt/snail-kernel
# COPY leaves the folder 0755; the kernel's loader requires its folder private (0700)
RUN chmod 0700 /opt/snail-kernel
ENV PATH=/opt/snail/bin:$PATH \
    SNAIL_CACHE_DIR=/cache \
    SNAIL_KERNEL_DIR=/opt/snail-kernel \
    PYTHONUNBUFFERED=1
USER snail
WORKDIR /tmp
CMD ["snail-client", "--help"]
