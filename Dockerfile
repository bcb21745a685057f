# One image for every service of docker-compose.yml: the Dask scheduler, the Dask workers and the API. The
# scheduler and the workers import compabs's task module (workers.tasks), so they run this same image.
#   docker build -t compabs .
#
# Reproducible: the base image is pinned by digest and every Python package by version and hash
# (requirements.lock, which tests/test_lock.py keeps in sync with pyproject.toml), so two builds install the same
# files. The digest is that of python:3.11.13-slim-bookworm (CPython 3.11.13 on Debian 12), as public projects
# pin it (taken from them: the machine this was written on cannot reach Docker Hub); with a digest Docker ignores
# the tag, which today names a Debian 13 image. Check or move it with
#   docker buildx imagetools inspect python:3.11.13-slim-bookworm
# and regenerate the lock after a change of dependencies with the command at its top.
FROM python:3.11-slim@sha256:86adf8dbadc3d6e82ee5dd2c74bec2e1c2467cdad47886280501df722372d2e1

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1

# The workers' Dask configuration (glibc malloc settings for their large numpy temporaries; see the file).
# /etc/dask is read by every Dask process of the image.
COPY workers/dask.yaml /etc/dask/compabs.yaml

# MONA translates 'ltl' specifications' formulas to automata (workers/automata.py): Debian's package.
RUN apt-get update && apt-get install -y --no-install-recommends mona && rm -rf /var/lib/apt/lists/*

WORKDIR /opt/compabs
# The dependencies first, in a layer of their own: a change of compabs's code does not reinstall them.
# --require-hashes: each file must match the lock's hash. ply and astutils (dd's) are published as source only;
# pip builds them in an isolated environment whose setuptools the constraint pins to the lock's. dd's wheel
# bundles CUDD: no compiler needed.
COPY requirements.lock ./
RUN echo "setuptools==$(sed -n 's/^setuptools==\([^ ]*\).*/\1/p' requirements.lock)" > /tmp/build-constraints.txt \
 && PIP_CONSTRAINT=/tmp/build-constraints.txt pip install --require-hashes -r requirements.lock \
 && rm /tmp/build-constraints.txt
COPY pyproject.toml README.md ./
COPY pipelines ./pipelines
COPY workers ./workers
COPY service ./service
COPY examples ./examples
# compabs itself, without resolving anything (its dependencies are the lock's), built with the lock's setuptools.
RUN pip install --no-deps --no-build-isolation . && pip check && rm -rf build
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
