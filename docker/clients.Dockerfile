# palpsim clients image: the thin haptic client palpsim-haptic (C++), the Python package's
# palpsim-batch, palpsim-view, palpsim-web (the browser station's gateway) and palpsim-igtl
# (3D Slicer's OpenIGTLink bridge), and palpsim-keys. CPU only; the build stage is
# server.Dockerfile's first layers (Docker shares them), the runtime stage holds the two
# executables with the libraries they link, and a Python venv with the package.
#
# Build from the repository root with BuildKit (Docker 23+ with buildx; on Debian 12's
# docker.io 20.10: DOCKER_BUILDKIT=1), as scripts/docker-test.sh does:
#   docker build -f docker/clients.Dockerfile -t palpsim-clients .
# Run against a server with this station's keys (docs/containers.md):
#   docker run --rm -v "$PWD/keys:/keys:ro" palpsim-clients palpsim-haptic --connect tcp://HOST:7420 \
#     --server-key /keys/server.key --client-key /keys/station1.key_secret --device press --seconds 5
#   docker run --rm -v "$PWD/keys:/keys:ro" -v "$PWD/out:/out" palpsim-clients palpsim-batch PLAN \
#     --connect tcp://HOST:7420 --server-key /keys/server.key --client-key /keys/station1.key_secret --out /out/run
#   docker run -d -p 8443:8080 -v "$PWD/keys:/keys:ro" palpsim-clients palpsim-web --connect tcp://HOST:7420 \
#     --server-key /keys/server.key --client-key /keys/station1.key_secret --host 0.0.0.0 --port 8080 \
#     --tls-cert /keys/web.crt --tls-key /keys/web.key --station-token-file /keys/station.token
#   docker run -d --network host -v "$PWD/keys:/keys:ro" palpsim-clients palpsim-igtl --connect tcp://HOST:7420 \
#     --server-key /keys/server.key --client-key /keys/station1.key_secret     # Slicer on this host: 127.0.0.1:18944
# Build args: JOBS (compile jobs, default: all cores), EXTRA_CA_CERTS (PEM text of CAs that
# pip must trust behind a TLS-inspecting proxy; build stage only).

# ---- build stage (these first layers are server.Dockerfile's, word for word)
FROM debian:12 AS build
RUN apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends \
      ca-certificates build-essential ninja-build ccache pkg-config python3 python3-venv \
      libinsighttoolkit5-dev libgdcm-dev libzmq3-dev cppzmq-dev libprotobuf-dev protobuf-compiler \
      catch2 libspdlog-dev libpng-dev libjpeg-dev libturbojpeg0-dev libzstd-dev zlib1g-dev \
      libegl-dev libgl-dev libopengl-dev \
 && rm -rf /var/lib/apt/lists/*
ARG EXTRA_CA_CERTS=""
RUN if [ -n "$EXTRA_CA_CERTS" ]; then \
      printf '%s\n' "$EXTRA_CA_CERTS" > /usr/local/share/ca-certificates/extra.crt && update-ca-certificates; fi
ENV PIP_CERT=/etc/ssl/certs/ca-certificates.crt PIP_DISABLE_PIP_VERSION_CHECK=1
RUN python3 -m venv /opt/venv && /opt/venv/bin/pip install -q --no-cache-dir 'cmake>=3.31,<5'

# the Python package's dependencies (no Ray: studies on a cluster install palpsim[ray]),
# from its pyproject.toml alone, so that a change to the sources does not install them
# again, into a venv at the path it keeps in the runtime stage
COPY clients/python/pyproject.toml /tmp/pyproject.toml
RUN --mount=type=cache,target=/root/.cache/pip \
    python3 -c 'import tomllib; print("\n".join(tomllib.load(open("/tmp/pyproject.toml", "rb"))["project"]["dependencies"]))' \
      > /tmp/requirements.txt \
 && python3 -m venv /opt/palpsim/venv && /opt/palpsim/venv/bin/pip install -q -r /tmp/requirements.txt

# palpsim-haptic, palpsim-keys and the generated protobuf modules of the Python package
# (ccache kept between builds in a BuildKit cache), then bin/ and lib/ of /opt/palpsim
COPY . /src
ARG JOBS=""
RUN --mount=type=cache,target=/root/.ccache \
    export CCACHE_DIR=/root/.ccache CCACHE_BASEDIR=/src CCACHE_MAXSIZE=2G \
 && /opt/venv/bin/cmake -S /src -B /build -G Ninja -DCMAKE_BUILD_TYPE=Release -DPALPSIM_CUDA=OFF \
      -DPython3_EXECUTABLE=/usr/bin/python3 -DCMAKE_C_COMPILER_LAUNCHER=ccache -DCMAKE_CXX_COMPILER_LAUNCHER=ccache \
 && nice -n 10 /opt/venv/bin/cmake --build /build -j ${JOBS:-$(nproc)} --target palpsim-haptic palpsim-keys palpsim_proto_py \
 && ccache -s | grep -E 'Hits|Misses' | head -2 \
 && /src/docker/collect-libs.sh /opt/palpsim /build/palpsim-haptic /build/palpsim-keys

# the package itself, less the libraries' own test suites (110 MB); the check imports what
# the tools use
RUN --mount=type=cache,target=/root/.cache/pip /opt/palpsim/venv/bin/pip install -q --no-deps /src/clients/python \
 && find /opt/palpsim/venv/lib -depth -type d -name tests -prune -exec rm -rf {} + \
 && /opt/palpsim/venv/bin/python -c 'import palpsim.batch, palpsim.view, palpsim.plots, palpsim.web, palpsim.igtl, \
      aiohttp.web, pyigtl, pyarrow.parquet, zmq; \
      assert zmq.has("curve"), "pyzmq without CURVE"'

# ---- the image: debian:12 with Python 3.11 (the venv's interpreter) and the clients
FROM debian:12
RUN apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends python3 \
 && apt-get clean && rm -rf /var/lib/apt/lists/*
COPY --from=build /opt/palpsim /opt/palpsim
RUN echo /opt/palpsim/lib > /etc/ld.so.conf.d/palpsim.conf && ldconfig
# the example plans, for palpsim-batch
COPY clients/python/examples /opt/palpsim/examples
ENV PATH=/opt/palpsim/bin:/opt/palpsim/venv/bin:$PATH MPLBACKEND=Agg
# palpsim-web's port as docs/containers.md runs it (--host 0.0.0.0 --port 8080, with TLS and
# a station token). palpsim-igtl serves OpenIGTLink, which has no login, on loopback only:
# its container runs with --network host beside Slicer, or connects out (--igtl-connect)
EXPOSE 8080
WORKDIR /work
CMD ["palpsim-haptic", "--help"]
