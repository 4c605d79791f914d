# GP-NARX hysteresis surrogate service.
#
#   docker build -t gpnarx .
#   docker run -p 8000:8000 gpnarx                       # serves the default registry
#   docker run -p 8000:8000 -e GPNARX_API_KEY=... -v /srv/registry:/registry gpnarx \
#       gpnarx serve --registry /registry --host 0.0.0.0 --port 8000
#   docker run -p 8000:8000 -e GPNARX_REGISTRY=s3://bucket/models -e AWS_ACCESS_KEY_ID=... \
#       -e AWS_SECRET_ACCESS_KEY=... gpnarx               # a registry on object storage
#
# Two stages: the first builds the gpnarx wheel and the wheels of everything it needs (with the s3,
# dask and train extras; pinned with hashes by requirements.lock), the second installs them from that folder alone, so the image holds an installed
# package (shipped configs as package data), not a checkout. The same image runs `gpnarx serve`,
# the offline commands (`gpnarx train ... --scheduler`) and Dask workers (`dask worker ADDRESS`).
# The default registry (Bouc-Wen and BERT stand-in bundles) is built at image build time by
# `gpnarx build-defaults` (a few minutes on 2 cores), so the container is ready at first start.
# deploy/compose.yaml and deploy/k8s/ run it as replicas; docs/deploy.md describes both.

FROM python:3.11-slim AS build
ENV PIP_NO_CACHE_DIR=1 PIP_DISABLE_PIP_VERSION_CHECK=1
WORKDIR /src
COPY pyproject.toml README.md LICENSE ./
COPY gpnarx ./gpnarx
COPY model ./model
COPY operations ./operations
COPY storage ./storage
COPY training ./training
COPY service ./service
COPY cli ./cli
COPY client ./client
COPY configs ./configs
# the dependencies from the lock file with hashes (pip-compile --generate-hashes, see docs/deploy.md), then gpnarx
COPY requirements.lock ./
RUN pip wheel --require-hashes --no-deps -r requirements.lock -w /wheels \
    && pip wheel --no-deps . -w /wheels

FROM python:3.11-slim
ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    GPNARX_REGISTRY=/var/lib/gpnarx/registry \
    GPNARX_BLAS_THREADS=1 \
    MPLBACKEND=Agg

RUN groupadd --system --gid 10001 gpnarx \
    && useradd --system --uid 10001 --gid gpnarx --home-dir /home/gpnarx --create-home --shell /usr/sbin/nologin gpnarx \
    && mkdir -p /var/lib/gpnarx/registry \
    && chown -R gpnarx:gpnarx /var/lib/gpnarx

COPY --from=build /wheels /tmp/wheels
RUN pip install --no-index --find-links /tmp/wheels "gpnarx[s3,dask,train]" \
    && rm -rf /tmp/wheels \
    && python -c "import gpnarx.service.app, gpnarx.storage.bundle, gpnarx.cli.main"

USER gpnarx
WORKDIR /home/gpnarx
# Default registry at image build (training runs as the unprivileged user into its own folder).
RUN gpnarx build-defaults --registry "$GPNARX_REGISTRY"

EXPOSE 8000
HEALTHCHECK --interval=30s --timeout=5s --start-period=120s --retries=3 \
    CMD ["python", "-c", "import sys, urllib.request; sys.exit(0 if urllib.request.urlopen('http://127.0.0.1:8000/health/ready', timeout=4).status == 200 else 1)"]
CMD ["gpnarx", "serve", "--host", "0.0.0.0", "--port", "8000"]
