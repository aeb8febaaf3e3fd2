# cadreg registration service: HTTP on 8080, zenoh on 7447, site bundles on the /sites volume.
FROM python:3.11-slim

# Open3D imports headless only with these Debian libraries (DESIGN §9).
RUN apt-get update \
    && apt-get install -y --no-install-recommends libusb-1.0-0 libgl1 libegl1 libx11-6 \
    && rm -rf /var/lib/apt/lists/*

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    OMP_NUM_THREADS=1 \
    OPENBLAS_NUM_THREADS=1 \
    MKL_NUM_THREADS=1

WORKDIR /app

# Dependency layer first: it changes only when pyproject.toml does, so code edits rebuild in seconds.
COPY pyproject.toml ./
RUN python -c "import tomllib; deps = tomllib.load(open('pyproject.toml', 'rb'))['project']['dependencies']; open('/tmp/requirements.txt', 'w').write('\n'.join(deps))" \
    && pip install -r /tmp/requirements.txt

COPY README.md ./
COPY cadreg ./cadreg
COPY service ./service
COPY clients ./clients
RUN pip install --no-deps .

RUN useradd --create-home --uid 10001 cadreg \
    && mkdir -p /sites \
    && chown cadreg:cadreg /sites
USER cadreg
# numba's compiled loops (cadreg/localize: `compile_loops`) are cached where this user may write, and compiled once
# here rather than by the first request of every worker.
ENV NUMBA_CACHE_DIR=/home/cadreg/.cache/numba
RUN python -c "from cadreg.localize.localizer import compile_loops; compile_loops()"

ENV CADREG_SITES_DIR=/sites \
    CADREG_HOST=0.0.0.0 \
    CADREG_PORT=8080 \
    CADREG_ZENOH_LISTEN='["tcp/0.0.0.0:7447"]'
VOLUME ["/sites"]
EXPOSE 8080 7447

HEALTHCHECK --interval=30s --timeout=5s --start-period=60s --retries=3 \
    CMD ["python", "-c", "import sys, urllib.request; sys.exit(0 if urllib.request.urlopen('http://127.0.0.1:8080/healthz', timeout=4).status == 200 else 1)"]

CMD ["cadreg", "serve", "--host", "0.0.0.0", "--sites", "/sites"]
