# gaitmon API and worker image (the same image runs `gaitmon serve`, `gaitmon worker` and `gaitmon migrate`).
FROM python:3.11-slim

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    GAITMON_DATA_DIR=/data

WORKDIR /app
# Dependencies change less often than the code: install them in their own layer.
COPY pyproject.toml README.md ./
RUN python -c "import tomllib; print('\n'.join(tomllib.load(open('pyproject.toml', 'rb'))['project']['dependencies']))" \
        > /tmp/requirements.txt \
    && pip install -r /tmp/requirements.txt

COPY pipeline ./pipeline
COPY server ./server
# server/migrations links to the top-level Alembic scripts; the wheel ships them inside the service.
COPY migrations ./migrations
RUN pip install --no-deps . \
    && useradd --system --uid 10001 --home-dir /data --create-home gaitmon

USER gaitmon
EXPOSE 8000
HEALTHCHECK --interval=15s --timeout=5s --start-period=20s --retries=3 \
    CMD python -c "import urllib.request; urllib.request.urlopen('http://127.0.0.1:8000/healthz', timeout=4)"
CMD ["gaitmon", "serve", "--host", "0.0.0.0", "--port", "8000"]
