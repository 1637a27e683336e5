# Multi-stage build of `radiance serve`: a Rust builder, then a slim runtime
# that runs as a non-root user with the data directory on a volume.
FROM rust:1.95-slim-bookworm AS build
# openh264-sys2 (the default `mp4` feature) compiles OpenH264's C++ source;
# the slim image has only gcc.
RUN apt-get update \
    && apt-get install -y --no-install-recommends g++=4:12.* \
    && rm -rf /var/lib/apt/lists/*
WORKDIR /src
COPY Cargo.toml Cargo.lock ./
COPY src ./src
# The web app is compiled into the binary (include_str! in src/api/web.rs).
COPY web ./web
# The release profile keeps line tables for profiling; the image's binary
# needs none of them (132 MB with them).
ENV CARGO_PROFILE_RELEASE_DEBUG=0 \
    CARGO_PROFILE_RELEASE_STRIP=debuginfo
RUN cargo build --release --locked --bin radiance

FROM debian:bookworm-slim
# COLMAP poses photo-only uploads (CPU SIFT, no CUDA); ffmpeg takes frames from videos;
# ca-certificates: the root certificates HTTPS to an S3 object store needs (--object-store s3://).
RUN apt-get update \
    && apt-get install -y --no-install-recommends curl=7.* colmap=3.8-* ffmpeg=7:5.1.* ca-certificates=202* \
    && rm -rf /var/lib/apt/lists/* \
    && groupadd --system --gid 10001 radiance \
    && useradd --system --uid 10001 --gid 10001 --home-dir /data --no-create-home radiance \
    && mkdir -p /data \
    && chown 10001:10001 /data
# The licence texts (MIT OR Apache-2.0) travel with the binary.
COPY LICENSE-MIT LICENSE-APACHE /usr/share/doc/radiance/
COPY --from=build /src/target/release/radiance /usr/local/bin/radiance
# Numeric, so the runtime (and Kubernetes' runAsNonRoot) can tell it is not root.
USER 10001:10001
ENV RADIANCE_ADDR=0.0.0.0:8080 \
    RADIANCE_DATA_DIR=/data
VOLUME ["/data"]
EXPOSE 8080
HEALTHCHECK --interval=30s --timeout=3s --start-period=5s CMD ["curl", "-fsS", "http://127.0.0.1:8080/healthz"]
ENTRYPOINT ["radiance", "serve"]
