# syntax=docker/dockerfile:1
# Multi-stage: build wheels with the pinned constraints, then a slim runtime as a non-root user.
# VLP_DEMO=0: a production container never seeds the demo room (run with -e VLP_DEMO=1 to try it).
FROM python:3.11-slim AS build
WORKDIR /src
COPY pyproject.toml constraints.txt README.md ./
COPY app ./app
RUN python -m pip install --no-cache-dir --upgrade pip \
 && python -m pip wheel --no-cache-dir -c constraints.txt --wheel-dir /wheels .

FROM python:3.11-slim AS runtime
ENV PYTHONDONTWRITEBYTECODE=1 PYTHONUNBUFFERED=1 \
    OPENBLAS_NUM_THREADS=1 OMP_NUM_THREADS=1 MKL_NUM_THREADS=1 \
    VLP_DATA_DIR=/data \
    VLP_DEMO=0 \
    NUMBA_CACHE_DIR=/home/vlp/.cache/numba
# numba caches the solver's compiled kernels there (site-packages is not writable by vlp);
# without it they would be compiled again at every start.
RUN useradd --create-home --uid 10001 vlp && mkdir -p /data && chown vlp:vlp /data
COPY --from=build /wheels /wheels
RUN python -m pip install --no-cache-dir /wheels/*.whl && rm -rf /wheels
USER vlp
WORKDIR /home/vlp
# Compile the solver's kernels into NUMBA_CACHE_DIR now, so that the container's first start
# loads them (numba recompiles, once, if the host's CPU differs from the build machine's).
RUN python -c "from app.vlp.solvers import warm_up; warm_up()"
VOLUME ["/data"]
EXPOSE 8000
HEALTHCHECK CMD ["python", "-c", "import urllib.request,sys; sys.exit(urllib.request.urlopen('http://127.0.0.1:8000/healthz').status != 200)"]
CMD ["vlp", "serve", "--host", "0.0.0.0", "--port", "8000"]
