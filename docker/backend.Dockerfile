# The library service: API + the built frontend. No numerical reconstruction code is installed.
FROM node:20-bookworm-slim AS frontend
WORKDIR /src/frontend
COPY frontend/package.json frontend/package-lock.json ./
RUN npm ci --no-audit --no-fund
COPY frontend/ ./
RUN npm run build

FROM python:3.11-slim-bookworm
ENV PYTHONDONTWRITEBYTECODE=1 PYTHONUNBUFFERED=1
WORKDIR /app
COPY pyproject.toml README.md ./
COPY backend/ backend/
COPY worker/ worker/
COPY rig_agent/ rig_agent/
RUN pip install --no-cache-dir ".[backend]"
COPY --from=frontend /src/frontend/dist frontend/dist
RUN useradd --system --uid 1000 hammurabi && mkdir -p /data && chown hammurabi /data
USER hammurabi
EXPOSE 8000
CMD ["hammurabi", "serve", "--host", "0.0.0.0", "--port", "8000"]
