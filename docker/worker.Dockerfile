# Reconstruction worker: numpy/scipy/OpenCV pipeline behind Celery.
FROM python:3.11-slim-bookworm
ENV PYTHONDONTWRITEBYTECODE=1 PYTHONUNBUFFERED=1
RUN apt-get update && apt-get install -y --no-install-recommends libgl1 libgomp1 libusb-1.0-0 \
    && rm -rf /var/lib/apt/lists/*
WORKDIR /app
COPY pyproject.toml README.md ./
COPY backend/ backend/
COPY worker/ worker/
COPY rig_agent/ rig_agent/
RUN pip install --no-cache-dir ".[backend,worker]"
RUN useradd --system --uid 1000 hammurabi && mkdir -p /data && chown hammurabi /data
USER hammurabi
CMD ["hammurabi", "worker", "--concurrency", "1"]
