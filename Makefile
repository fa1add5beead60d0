# renderfarm: `make demo` renders the Cornell box (or SCENE=...) on a local farm; `make test` runs every test.
SHELL := /bin/bash
VENV := .venv
PY := $(VENV)/bin/python
BUILD := build/worker
JOBS ?= 2

.PHONY: all deps build proto worker web blender-addon blender-deps test test-cpp test-py test-web test-deploy lint demo stop bench clean settings-doc openapi channels

all: build

deps:
	@scripts/install-deps.sh

# Python gRPC stubs are generated at build time, never committed.
proto: deps
	@$(PY) -m grpc_tools.protoc -I proto --python_out=server --pyi_out=server \
	  --grpc_python_out=server proto/renderfarm/v1/*.proto

worker: deps
	@cmake -S worker -B $(BUILD) -G Ninja -DCMAKE_BUILD_TYPE=Release >/dev/null
	@cmake --build $(BUILD) -j $(JOBS)

# The dashboard: npm packages as locked in web/package-lock.json (installed again only when the
# lock file changed), then type check and bundle into web/dist, which the server serves at /.
web: deps
	@cd web && { [ node_modules/.package-lock.json -nt package-lock.json ] || \
	  npm ci --no-audit --no-fund --loglevel=error; } && npm run --silent build

build: proto worker web

# The Blender add-on (integrations/blender) as the zip Blender installs from disk.
BLENDER_ADDON_ZIP ?= build/renderfarm-blender.zip
blender-addon:
	@python3 integrations/blender/build.py $(BLENDER_ADDON_ZIP)

# Blender's bpy module in .venv-blender, for the add-on's tests.
blender-deps:
	@scripts/install-deps.sh --blender

# web/openapi.json (the dashboard's TypeScript types are generated from it; a test fails while stale).
openapi: proto
	$(VENV)/bin/python scripts/openapi_json.py

# docs/settings.md's table, from server/renderfarm/domain/jobspec.py SETTINGS (a test fails while stale).
settings-doc: proto
	$(VENV)/bin/python scripts/settings_doc.py

# docs/usage.md's layers table, from server/renderfarm/domain/channels.py (a test fails while stale).
channels: proto
	$(VENV)/bin/python scripts/channel_table.py

lint: deps
	$(VENV)/bin/ruff check server tests bench examples integrations
	$(VENV)/bin/ruff format --check server tests bench examples integrations

test-cpp: worker
	ctest --test-dir $(BUILD) --output-on-failure -j $(JOBS)

test-py: build blender-deps
	$(PY) -m pytest -q server/tests tests --ignore-glob='tests/test_deploy*'

# The dashboard's unit tests (web/test/*.test.ts): type checked, bundled by esbuild into
# web/dist-test and run by Node's test runner.
test-web: web
	@cd web && npm run --silent test

test: lint test-web test-cpp test-py test-deploy

# ---- deploy: compose, Kubernetes and image checks (offline), and the multi-host test over
# network namespaces (root). Tools from scripts/install-deps.sh --deploy-tools.
test-deploy: build
	@scripts/install-deps.sh --deploy-tools
	$(PY) -m pytest -q tests/test_deploy_static.py tests/test_deploy_image.py \
	  tests/test_deploy_multihost.py

# SCENE: an example's short name (cornell-box, studio, hinged-box) or a .glb/.gltf path; it is
# checked before anything is built or started.
demo:
	@scripts/demo.sh --resolve "$(SCENE)" >/dev/null
	@$(MAKE) --no-print-directory build
	@scripts/demo.sh "$(SCENE)"

stop:
	@scripts/demo.sh stop

bench: build
	@mkdir -p bench/results
	@set -e; for b in bench/*.py; do echo "== $$b"; $(PY) $$b; done

clean:
	rm -rf build .pytest_cache .ruff_cache out
