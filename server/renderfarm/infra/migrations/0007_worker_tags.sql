-- Worker pools: the worker tags a job requires (only workers announcing all of them render it).
ALTER TABLE jobs ADD COLUMN require_tags text[] NOT NULL DEFAULT '{}';
