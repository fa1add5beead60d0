"""The server's faces: REST (FastAPI), gRPC, Server-Sent Events, session cookies, the web UI's
static files, Prometheus metrics, and running it all (server.py). Imports any layer but cli."""
