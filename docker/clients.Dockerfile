# palpsim clients image: the thin haptic client (C++) and the Python batch runner.
# Build from the repository root:  docker build -f docker/clients.Dockerfile -t palpsim-clients .
# Run a batch plan against a server:
#   docker run --rm -v $PWD/out:/out palpsim-clients palpsim-batch PLAN --connect tcp://HOST:5555 --out /out
FROM debian:12
WORKDIR /opt/palpsim
COPY . .
RUN PALPSIM_CUDA=OFF bash scripts/setup.sh && rm -rf /root/.cache/pip
ENV PATH=/opt/palpsim/.venv/bin:/opt/palpsim/build:$PATH
