"""Generated protobuf and gRPC modules of the renderfarm.v1 API (built by `make build`)."""
