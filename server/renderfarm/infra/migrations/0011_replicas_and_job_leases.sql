-- Scale-out (#39): several servers ("replicas") over one database form one farm. Each
-- unfinished job is owned by one replica at a time through its row in job_leases; `epoch` is
-- the fencing token: it grows by one each time another hold begins, and every write of an owner
-- (tiles, the job's row, its events) is made only while the row still names that replica and
-- epoch (docs/architecture.md, "Ownership"). Expiry is the database's clock (now()), so the
-- replicas' clocks do not matter. A released lease keeps its row (expired), so epochs never go
-- back; the row goes with its job.
CREATE TABLE job_leases (
    job_id      text PRIMARY KEY REFERENCES jobs (id) ON DELETE CASCADE,
    replica_id  text NOT NULL,
    epoch       bigint NOT NULL,
    expires_at  timestamptz NOT NULL
);
CREATE INDEX job_leases_replica ON job_leases (replica_id);

-- The replicas that have run against this database: where they answer, when they started,
-- their last heartbeat, and what they merged (GET /api/v1/replicas).
CREATE TABLE replicas (
    id              text PRIMARY KEY,
    addresses       jsonb NOT NULL DEFAULT '{}',
    started_at      timestamptz NOT NULL DEFAULT now(),
    heartbeat_at    timestamptz NOT NULL DEFAULT now(),
    batches_merged  bigint NOT NULL DEFAULT 0,
    merge_rate      double precision NOT NULL DEFAULT 0
);

-- Job control that reached a replica which does not own the job (pause, resume, cancel, an
-- update of priority or name): the owner applies it in its next background round and then
-- deletes the row; the replica that took the request waits for that and answers.
CREATE TABLE job_requests (
    id            bigserial PRIMARY KEY,
    job_id        text NOT NULL REFERENCES jobs (id) ON DELETE CASCADE,
    action        text NOT NULL,
    data          jsonb NOT NULL DEFAULT '{}',
    requested_at  timestamptz NOT NULL DEFAULT now()
);
CREATE INDEX job_requests_job ON job_requests (job_id);
