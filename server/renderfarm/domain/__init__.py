"""The render farm's rules, without I/O: job settings, states, tiling, merging, scheduling and
scene validation. Imports nothing of app, api, infra or cli (server/tests/test_layers.py)."""
