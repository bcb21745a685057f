# One image for every service of docker-compose.yml: the Dask scheduler, the Dask workers and the API. The
# scheduler and the workers import compabs's task module (workers.tasks), so they run this same image.
#   docker build -t compabs .
FROM python:3.11-slim

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1

# The workers' Dask configuration (glibc malloc settings for their large numpy temporaries; see the file).
# /etc/dask is read by every Dask process of the image.
COPY workers/dask.yaml /etc/dask/compabs.yaml

WORKDIR /opt/compabs
COPY pyproject.toml README.md ./
COPY pipelines ./pipelines
COPY workers ./workers
COPY service ./service
COPY examples ./examples
# dd's wheel bundles CUDD: no compiler needed.
RUN pip install . && rm -rf build
# The per-cell stage's numba kernels, compiled once here into the package's cache (readable by the user below,
# so no worker compiles them at its first task; numba would otherwise cache under that user's ~/.cache).
RUN python -c "import pipelines.abstraction.kernels as compiled; compiled.warm_up()"

# Not root. /data is the shared volume (Zarr relation stores, the SQLite job store, reports, figures); /tls the
# volume of the Dask cluster's TLS credentials, which `compabs credentials /tls` writes at deployment (the
# compose file's `credentials` service): the image holds no key, so no two deployments share one. A named volume
# takes its directory's owner and mode when it is first created.
RUN useradd --create-home --uid 10001 --user-group compabs \
 && mkdir /data /tls && chown compabs:compabs /data /tls && chmod 0700 /tls
USER compabs
WORKDIR /home/compabs
VOLUME ["/data"]
ENV COMPABS_DATA_DIR=/data

# 8000 the API, 8786 the Dask scheduler, 8787 its dashboard.
EXPOSE 8000 8786 8787
CMD ["compabs", "serve", "--host", "0.0.0.0", "--port", "8000", "--data", "/data"]
