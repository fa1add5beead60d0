-- A job's USD source (issue #41), recorded with the job at submit: two uploads that convert to
-- byte-identical glTF share one scene row (and scene_sources keeps the first upload's record),
-- so each job keeps the upload it was submitted with, for its EXR. A job submitted by
-- scene_sha256 has none (its EXR names the scene's record). Removed with its job.
CREATE TABLE job_scene_sources (
    job_id          text PRIMARY KEY REFERENCES jobs (id) ON DELETE CASCADE,
    source_format   text NOT NULL,
    source_sha256   text NOT NULL,
    source_filename text NOT NULL
);
