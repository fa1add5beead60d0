-- Planned sizes (samples per pixel) of a tile's next batches, from batch max(batches, 7) on
-- (scheduler.planned_batches): a resumed job renders the batches it would have rendered.
-- NULL: nothing planned (no noise threshold, a stopped tile, or a checkpoint from before this
-- column, which plans afresh from its merged state).
ALTER TABLE tiles ADD COLUMN batch_plan integer[];
