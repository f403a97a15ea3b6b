# palpsim-server image. By default the GPU server: the CUDA deformation backend, frames
# drawn by the NVIDIA driver's EGL and encoded by nvJPEG. With --build-arg VARIANT=cpu
# the CPU variant, for machines without a GPU: the CPU deformation, Mesa llvmpipe frames.
# The CUDA 13 toolchain (nvcc, cudart, CCCL, nvJPEG) comes from NVIDIA's PyPI wheels and
# stays in the build stage; the runtime stage holds the server, palpsim-keys, the
# libraries they link and the scenes.
#
# Build from the repository root with BuildKit (Docker 23+ with buildx; on Debian 12's
# docker.io 20.10: DOCKER_BUILDKIT=1), as scripts/docker-test.sh does:
#   docker build -f docker/server.Dockerfile -t palpsim-server:gpu .
#   docker build -f docker/server.Dockerfile --build-arg VARIANT=cpu -t palpsim-server:cpu .
# Run with keys/ made by palpsim-keys (docs/containers.md):
#   docker run --rm --gpus all -p 7420-7422:7420-7422 -v "$PWD/keys:/keys:ro" palpsim-server:gpu
# Build args: VARIANT (gpu|cpu), CUDA_ARCHITECTURES (default 90, the H100), JOBS
# (compile jobs, default: all cores), EXTRA_CA_CERTS (PEM text of CAs that pip must trust
# behind a TLS-inspecting proxy; build stage only).

ARG VARIANT=gpu

# ---- build stage: Debian's -dev packages, CMake from PyPI (Debian's 3.25 cannot find
# CUDA 13), the CUDA toolchain from PyPI wheels; the same first layers as clients.Dockerfile
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

# the CUDA 13.0 toolchain (the GPU machine's driver 580 runs CUDA 13.0) from NVIDIA's wheels,
# laid out as a toolkit in /usr/local/cuda, where CMake's FindCUDAToolkit looks; the wheels
# carry only libX.so.13, so the libX.so links that find_library needs are made here
ARG VARIANT
RUN if [ "$VARIANT" = gpu ]; then \
      /opt/venv/bin/pip install -q --no-cache-dir --target /tmp/cuda-wheels \
        nvidia-cuda-nvcc==13.0.88 nvidia-cuda-crt==13.0.88 nvidia-nvvm==13.0.88 \
        nvidia-cuda-runtime==13.0.96 nvidia-cuda-cccl==13.0.85 nvidia-nvjpeg==13.0.2.28 \
   && mv /tmp/cuda-wheels/nvidia/cu13 /usr/local/cuda-13.0 && rm -rf /tmp/cuda-wheels \
   && for f in /usr/local/cuda-13.0/lib/lib*.so.*; do \
        l=${f%%.so.*}.so; [ -e "$l" ] || ln -s "${f##*/}" "$l"; done \
   && ln -s lib /usr/local/cuda-13.0/lib64 \
   && mkdir -p /usr/local/cuda-13.0/targets/x86_64-linux \
   && ln -s ../../include /usr/local/cuda-13.0/targets/x86_64-linux/include \
   && ln -s ../../lib /usr/local/cuda-13.0/targets/x86_64-linux/lib \
   && ln -s cuda-13.0 /usr/local/cuda \
   && /usr/local/cuda/bin/nvcc --version | tail -2; \
    elif [ "$VARIANT" != cpu ]; then echo "VARIANT=$VARIANT: expected gpu or cpu" >&2; exit 1; fi

# the server and palpsim-keys (ccache kept between builds in a BuildKit cache), then the
# runtime folder /opt/palpsim: bin/, lib/ (docker/collect-libs.sh) and the scenes
COPY . /src
ARG CUDA_ARCHITECTURES=90
ARG JOBS=""
RUN --mount=type=cache,target=/root/.ccache \
    cuda=$([ "$VARIANT" = gpu ] && echo ON || echo OFF) \
 && export CCACHE_DIR=/root/.ccache CCACHE_BASEDIR=/src CCACHE_MAXSIZE=2G PATH=/usr/local/cuda/bin:$PATH \
 && /opt/venv/bin/cmake -S /src -B /build -G Ninja -DCMAKE_BUILD_TYPE=Release -DPALPSIM_CUDA=$cuda \
      -DCMAKE_CUDA_ARCHITECTURES=$CUDA_ARCHITECTURES -DPython3_EXECUTABLE=/usr/bin/python3 \
      -DCMAKE_C_COMPILER_LAUNCHER=ccache -DCMAKE_CXX_COMPILER_LAUNCHER=ccache -DCMAKE_CUDA_COMPILER_LAUNCHER=ccache \
 && nice -n 10 /opt/venv/bin/cmake --build /build -j ${JOBS:-$(nproc)} --target palpsim-server palpsim-keys \
 && ccache -s | grep -E 'Hits|Misses' | head -2 \
 && LD_LIBRARY_PATH=/usr/local/cuda/lib /src/docker/collect-libs.sh /opt/palpsim /build/palpsim-server /build/palpsim-keys \
 && mkdir -p /opt/palpsim/config && cp -r /src/config/scenes /opt/palpsim/config/

# ---- runtime stages: debian:12 and the EGL vendor (glvnd's loader comes with the server)
# CPU: Mesa's EGL and its llvmpipe renderer (the same EGL code path, on the CPU)
FROM debian:12 AS runtime-cpu
RUN apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends \
      libegl-mesa0 libgl1-mesa-dri \
 && apt-get clean && rm -rf /var/lib/apt/lists/*

# GPU: the NVIDIA container runtime mounts the driver's libraries (libcuda, libEGL_nvidia,
# ...) for these capabilities (graphics: EGL and OpenGL); glvnd finds libEGL_nvidia
# through this vendor file
FROM debian:12 AS runtime-gpu
RUN mkdir -p /usr/share/glvnd/egl_vendor.d \
 && printf '{"file_format_version": "1.0.0", "ICD": {"library_path": "libEGL_nvidia.so.0"}}\n' \
      > /usr/share/glvnd/egl_vendor.d/10_nvidia.json
ENV NVIDIA_VISIBLE_DEVICES=all NVIDIA_DRIVER_CAPABILITIES=compute,graphics,utility

# ---- the image: the chosen runtime and the server
FROM runtime-${VARIANT}
COPY --from=build /opt/palpsim /opt/palpsim
RUN echo /opt/palpsim/lib > /etc/ld.so.conf.d/palpsim.conf && ldconfig \
 && mkdir -p /var/cache/palpsim /keys
# prepared patients are cached here (mount a volume to keep them across containers)
ENV PATH=/opt/palpsim/bin:$PATH PALPSIM_CACHE=/var/cache/palpsim
WORKDIR /opt/palpsim
# control, poses, frames and bricks (control port + 1, + 2)
EXPOSE 7420 7421 7422
ENTRYPOINT ["palpsim-server"]
# the phantom scene (deformation, frames and bricks), on every interface, which needs CURVE:
# keys/ from palpsim-keys mounted at /keys (docs/security.md)
CMD ["--scene", "/opt/palpsim/config/scenes/lumbar_phantom.textproto", "--bind", "tcp://0.0.0.0:7420", \
     "--curve-secret", "/keys/server.key_secret", "--allow", "/keys/allowed"]
