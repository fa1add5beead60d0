-- Albedo and normal sums of a tile (float32 little-endian), apart from its statistics: they
-- change only during each pixel's first 16 samples, so checkpoints write them only while they
-- change. NULL: none yet, or a checkpoint from before this column, whose accumulators hold all
-- six arrays (float64).
ALTER TABLE tiles ADD COLUMN aovs bytea;

-- Checkpointed floats do not compress: store them out of line without trying (TOAST's pglz
-- would spend more time failing to compress a tile than writing it).
ALTER TABLE tiles ALTER COLUMN accumulators SET STORAGE EXTERNAL;
ALTER TABLE tiles ALTER COLUMN aovs SET STORAGE EXTERNAL;

-- Tiles with at least one merged batch (all of them: a full-frame preview exists). Jobs stored
-- before this column count their stopped tiles, a lower bound.
ALTER TABLE jobs ADD COLUMN tiles_previewed integer NOT NULL DEFAULT 0;
UPDATE jobs SET tiles_previewed = tiles_done;
