# One image for all three roles: snail-garbler, snail-evaluator, snail-client.
FROM python:3.11-slim

# iproute2: `tc netem` for latency experiments (the compose services add NET_ADMIN)
RUN apt-get update \
 && apt-get install -y --no-install-recommends iproute2 \
 && rm -rf /var/lib/apt/lists/*

WORKDIR /app
COPY pyproject.toml README.md ./
COPY snail_common ./snail_common
COPY snail_client ./snail_client
COPY snail_garbler ./snail_garbler
COPY snail_evaluator ./snail_evaluator
RUN pip install --no-cache-dir .

# compiled circuits (mount a volume here to keep them across restarts)
ENV SNAIL_CACHE_DIR=/cache
RUN mkdir -p /cache /tls
CMD ["snail-client", "--help"]
