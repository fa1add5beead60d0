-- Job control: the states paused and waiting, the jobs a job waits for (`after`, column after_jobs), and the basis
-- of each planned batch size of a tile, which a continue replays under the new settings.
ALTER TABLE jobs DROP CONSTRAINT jobs_state_check;
ALTER TABLE jobs ADD CONSTRAINT jobs_state_check
    CHECK (state IN ('queued', 'running', 'completed', 'failed', 'cancelled', 'paused',
                     'waiting'));
ALTER TABLE jobs ADD COLUMN after_jobs text[] NOT NULL DEFAULT '{}';
DROP INDEX jobs_unfinished;
CREATE INDEX jobs_unfinished ON jobs (state)
    WHERE state IN ('queued', 'running', 'paused', 'waiting');

-- Per planned batch (from batch 7 on, in order): [samples per pixel planned, merged samples per
-- pixel and relative error of the tile when it was planned (null: not finite), samples per pixel
-- before the batch]. NULL: none recorded (no noise threshold, or a checkpoint from before this
-- column; a continue then renders such a tile again from its first sample).
ALTER TABLE tiles ADD COLUMN plan_basis jsonb;
