# palpsim server image: Debian 12 with the project built by its own setup script.
# Build from the repository root:  docker build -f docker/server.Dockerfile -t palpsim-server .
# Run with keys (README, "Security"; keys/ made by palpsim-keys):
#   docker run --rm -p 5555-5556:5555-5556 -v "$PWD/keys:/keys:ro" palpsim-server --bind tcp://0.0.0.0:5555 \
#     --curve-secret /keys/server.key_secret --allow /keys/allowed
# or, on a trusted network only, in plain text: ... palpsim-server --bind tcp://0.0.0.0:5555 --insecure
# (for a GPU, use an NVIDIA CUDA base image with the same steps and --gpus all)
FROM debian:12
WORKDIR /opt/palpsim
COPY . .
RUN PALPSIM_CUDA=OFF bash scripts/setup.sh && rm -rf /root/.cache/pip
EXPOSE 5555 5556
ENTRYPOINT ["/opt/palpsim/build/palpsim-server"]
