-- Initial schema: scenes by content hash, jobs, tiles with checkpointed accumulators and stop
-- records, workers and an event log. States mirror renderfarm.v1.JobState (jobs.proto).

CREATE TABLE scenes (
    sha256      text PRIMARY KEY CHECK (sha256 ~ '^[0-9a-f]{64}$'),
    format      text NOT NULL CHECK (format IN ('glb', 'gltf')),
    filename    text NOT NULL,
    size_bytes  bigint NOT NULL,
    data        bytea NOT NULL,
    created_at  timestamptz NOT NULL DEFAULT now()
);

CREATE TABLE jobs (
    id              text PRIMARY KEY,
    name            text NOT NULL,
    state           text NOT NULL
                    CHECK (state IN ('queued', 'running', 'completed', 'failed', 'cancelled')),
    settings        jsonb NOT NULL,
    scene_sha256    text NOT NULL REFERENCES scenes (sha256),
    error           text NOT NULL DEFAULT '',
    created_at      timestamptz NOT NULL DEFAULT now(),
    started_at      timestamptz,
    finished_at     timestamptz,
    elapsed_s       double precision NOT NULL DEFAULT 0,
    samples_merged  bigint NOT NULL DEFAULT 0,
    mean_spp        double precision NOT NULL DEFAULT 0,
    error_estimate  double precision,
    tiles_total     integer NOT NULL DEFAULT 0,
    tiles_done      integer NOT NULL DEFAULT 0
);
CREATE INDEX jobs_created ON jobs (created_at DESC, id DESC);
CREATE INDEX jobs_unfinished ON jobs (state) WHERE state IN ('queued', 'running');

CREATE TABLE tiles (
    job_id        text NOT NULL REFERENCES jobs (id) ON DELETE CASCADE,
    tile_index    integer NOT NULL,
    samples       integer NOT NULL,
    batches       integer NOT NULL,
    nonfinite     bigint NOT NULL DEFAULT 0,
    error         double precision,
    accumulators  bytea NOT NULL,
    stop_batch    integer,
    stop_spp      integer,
    stop_error    double precision,
    stop_reason   text,
    updated_at    timestamptz NOT NULL DEFAULT now(),
    PRIMARY KEY (job_id, tile_index)
);

CREATE TABLE workers (
    id            text PRIMARY KEY,
    hostname      text NOT NULL,
    cores         integer NOT NULL,
    version       text NOT NULL,
    connected_at  timestamptz NOT NULL,
    last_seen     timestamptz NOT NULL,
    connected     boolean NOT NULL
);

CREATE TABLE events (
    id      bigserial PRIMARY KEY,
    job_id  text REFERENCES jobs (id) ON DELETE CASCADE,
    kind    text NOT NULL,
    data    jsonb NOT NULL,
    at      timestamptz NOT NULL DEFAULT now()
);
CREATE INDEX events_job ON events (job_id, id);
