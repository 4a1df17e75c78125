# cortexloc service: CPU torch, one worker (a map lives in one process), state on the /data volume.
FROM python:3.11-slim

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    CORTEXLOC_DATA_DIR=/data \
    CORTEXLOC_HOST=0.0.0.0 \
    CORTEXLOC_PORT=8000

WORKDIR /app
COPY pyproject.toml constraints.txt README.md ./
COPY common ./common
COPY models ./models
COPY storage ./storage
COPY service ./service
# The CPU wheel of torch from PyTorch's CPU index; the constraints pin its version for every install.
RUN pip install --extra-index-url https://download.pytorch.org/whl/cpu -c constraints.txt . \
    && useradd --create-home --uid 10001 cortexloc \
    && mkdir -p /data && chown cortexloc /data

USER cortexloc
# The backbones' ONNX exports, built from the installed weights now rather than at the first start.
RUN cortexloc weights export
VOLUME ["/data"]
EXPOSE 8000
HEALTHCHECK --interval=30s --timeout=5s --start-period=120s --retries=3 \
    CMD python -c "import urllib.request,sys; sys.exit(urllib.request.urlopen('http://127.0.0.1:8000/healthz', timeout=4).status != 200)"
CMD ["cortexloc", "serve", "--host", "0.0.0.0", "--port", "8000", "--data-dir", "/data"]
