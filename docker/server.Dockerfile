# palpsim server image: Debian 12 with the project built by its own setup script.
# Build from the repository root:  docker build -f docker/server.Dockerfile -t palpsim-server .
# Run:  docker run --rm -p 5555:5555 palpsim-server --bind tcp://0.0.0.0:5555 --insecure
# (for a GPU, use an NVIDIA CUDA base image with the same steps and --gpus all)
FROM debian:12
WORKDIR /opt/palpsim
COPY . .
RUN PALPSIM_CUDA=OFF bash scripts/setup.sh && rm -rf /root/.cache/pip
EXPOSE 5555 5556
ENTRYPOINT ["/opt/palpsim/build/palpsim-server"]
