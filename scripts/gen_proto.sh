#!/usr/bin/env bash
# Regenerates esiaf/proto/esiaf_pb2.py from proto/esiaf.proto.
# The protoc bundled with grpcio-tools must not be newer than the protobuf
# runtime pinned in pyproject.toml (gencode 7.35.x needs protobuf >= 7.35).
set -euo pipefail
cd "$(dirname "$0")/.."
python -m grpc_tools.protoc --version
python -m grpc_tools.protoc -Iproto --python_out=esiaf/proto --pyi_out=esiaf/proto proto/esiaf.proto
