-- KHR_materials_variants: a job with settings.variant "all" renders one image per variant of
-- its scene, as an animation does per frame; the variants' names, in the scene's order, are
-- kept with the job (its tiles, images and frame list follow them). Empty for every other job.
ALTER TABLE jobs ADD COLUMN variants text[] NOT NULL DEFAULT '{}';
