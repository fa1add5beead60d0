-- Animation jobs: how many of a job's frames have every tile stopped (a still has one frame).
ALTER TABLE jobs ADD COLUMN frames_done integer NOT NULL DEFAULT 0;
UPDATE jobs SET frames_done = 1 WHERE tiles_total > 0 AND tiles_done = tiles_total;
