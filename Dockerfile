# volumesh: one image for the gateway and the workers (docker-compose.yml picks the command).
# GPU workers build it with TORCH_INDEX=https://download.pytorch.org/whl/cu124.

FROM node:20-bookworm-slim AS web
WORKDIR /build
COPY package.json package-lock.json ./
# three.js (the viewer and its Draco decoder) is served by the gateway; nothing comes from a CDN.
RUN npm ci --no-audit --no-fund --loglevel=error

FROM python:3.11-slim-bookworm
ARG TORCH_INDEX=https://download.pytorch.org/whl/cpu
RUN apt-get update \
    && apt-get install -y --no-install-recommends libgomp1 libusb-1.0-0 \
    && rm -rf /var/lib/apt/lists/*
WORKDIR /opt/volumesh
COPY pyproject.toml README.md ./
COPY app app
COPY workers workers
COPY pipeline pipeline
COPY agent agent
COPY static static
COPY --from=web /build/node_modules/three node_modules/three
RUN pip install --no-cache-dir --index-url "$TORCH_INDEX" torch \
    && pip install --no-cache-dir .
RUN useradd --create-home --uid 10001 volumesh && mkdir /data && chown volumesh /data
USER volumesh
ENV VOLUMESH_DATA_DIR=/data PYTHONUNBUFFERED=1
VOLUME /data
EXPOSE 8000
HEALTHCHECK --interval=10s --timeout=3s --retries=3 \
    CMD python -c "import urllib.request; urllib.request.urlopen('http://127.0.0.1:8000/healthz', timeout=2)"
CMD ["volumesh", "serve", "--host", "0.0.0.0", "--port", "8000"]
