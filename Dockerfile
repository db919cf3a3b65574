# One image for every node of a datagen cluster: the Ray head (which also runs `datagen serve`) and
# the Ray workers. One Python, one Ray, one datagen everywhere, as Ray requires.
#
#   docker build -t datagen:local .                                              # CPU image
#   docker build -t datagen:cuda --build-arg TORCH_INDEX=https://download.pytorch.org/whl/cu126 .
#
# The CUDA build of torch carries its own CUDA runtime, so GPU workers keep the same Python 3.11
# base (and so the same Python and Ray as every other node); the host needs only the NVIDIA driver
# and container toolkit. BASE_IMAGE may name another Debian-based image with Python 3.11 as
# `python` (a CUDA base with Python installed, say); run GPU workers with --refiner-gpus.
ARG BASE_IMAGE=python:3.11-slim-bookworm
FROM ${BASE_IMAGE}

ARG TORCH_VERSION=2.13.0
ARG TORCH_INDEX=https://download.pytorch.org/whl/cpu
ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    OPENBLAS_NUM_THREADS=1 \
    OMP_NUM_THREADS=1 \
    DATAGEN_HOME=/var/lib/datagen

# libgomp1: the OpenMP runtime of Open3D (the poisson refiner) and torch; tini reaps Ray's children.
RUN apt-get update \
    && apt-get install -y --no-install-recommends libgomp1 tini \
    && rm -rf /var/lib/apt/lists/*

# torch first and pinned, from the index that matches the base (CPU wheels by default).
RUN python -m pip install "torch==${TORCH_VERSION}" --index-url "${TORCH_INDEX}"

# What Open3D's module links against (libX11, libGL, libudev): without them `import open3d` fails,
# even headless, and so does the poisson refiner (a slim base has none of them).
RUN apt-get update \
    && apt-get install -y --no-install-recommends libx11-6 libgl1 libudev1 \
    && rm -rf /var/lib/apt/lists/*

WORKDIR /opt/datagen
COPY pyproject.toml README.md SCHEMA.md ./
COPY reader ./reader
COPY datagen ./datagen
COPY schemas ./schemas
COPY storage ./storage
COPY jobs ./jobs
COPY examples ./examples
# ./reader packages storage and schemas (the light distribution datagen depends on): one resolve for both.
RUN python -m pip install ./reader ".[s3,poisson,cluster]" && python -c "import datagen, ray, embreex, highspy, s3fs, open3d"

RUN useradd --create-home --uid 1000 datagen && mkdir -p /var/lib/datagen && chown datagen /var/lib/datagen
USER datagen
ENTRYPOINT ["/usr/bin/tini", "--"]
CMD ["datagen", "--help"]
