# PRANet registration service: onnxruntime + Open3D ICP behind FastAPI/uvicorn. No torch in this image.
#   docker build -t pranet .
#   docker run --rm -p 8000:8000 pranet            # add -e PRANET_API_KEY=... to require a bearer token
# It runs as uid 10001 and writes nothing at run time, so a read-only root filesystem works
# (docker run --read-only; deploy/k8s). The batch client is in it too: pranet-client register-many (deploy/k8s/batch).
# Replicas behind nginx: deploy/compose.yaml.
# The model shipped in the wheel (pranet.model: model/default/*.onnx, card.json) is served by default;
# mount another one with -v /path/to/model:/model:ro -e PRANET_MODEL_DIR=/model.

# --- build: the project's wheel (setuptools from PyPI, in pip's isolated build environment) ----------
FROM python:3.11-slim AS build
WORKDIR /src
COPY pyproject.toml README.md ./
COPY core/ core/
COPY engine/ engine/
COPY model/ model/
COPY training/ training/
COPY service/ service/
COPY client/ client/
RUN pip wheel --no-cache-dir --no-deps . -w /dist

# --- runtime ------------------------------------------------------------------------------------------
FROM python:3.11-slim

# open3d-cpu's libOpen3D links libusb-1.0, libGL, libEGL, libX11 and libidn2 (no display is used: ICP only);
# checked with ldd in a Debian trixie minbase root, the base of python:3.11-slim.
# Debian package versions are not pinned: the security archive replaces them; Python packages are.
# hadolint ignore=DL3008
RUN apt-get update \
    && apt-get install -y --no-install-recommends libusb-1.0-0 libgl1 libegl1 libx11-6 libidn2-0 \
    && rm -rf /var/lib/apt/lists/*

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    PRANET_HOST=0.0.0.0 \
    PRANET_PORT=8000 \
    OMP_WAIT_POLICY=PASSIVE

# The wheel with the service extra only, and httpx for pranet-client (the batch Job runs this image), every
# dependency pinned by requirements/service.lock.
COPY requirements/service.lock /tmp/service.lock
COPY --from=build /dist/ /tmp/wheels/
RUN pip install --no-cache-dir -c /tmp/service.lock "$(ls /tmp/wheels/pranet-*.whl)[service]" httpx \
    && rm -rf /tmp/wheels /tmp/service.lock \
    && python -c "import importlib.util as u; assert u.find_spec('torch') is None, 'torch must not be in the image'" \
    && python -c "from pranet.engine.runtime import RewardModel; print('model', RewardModel.load(threads=1).info())"

# A non-root user with a fixed numeric id (mounts and Kubernetes runAsUser can rely on it).
RUN groupadd --gid 10001 pranet \
    && useradd --create-home --uid 10001 --gid 10001 --shell /usr/sbin/nologin pranet
USER 10001:10001
WORKDIR /home/pranet

EXPOSE 8000
# /ready (the model is loaded), with the API key when one is set: the probe reads PRANET_API_KEY and PRANET_PORT.
HEALTHCHECK --interval=10s --timeout=5s --start-period=60s --retries=3 \
    CMD ["python", "-m", "pranet.service.probe", "ready"]
CMD ["pranet-serve", "--host", "0.0.0.0"]
