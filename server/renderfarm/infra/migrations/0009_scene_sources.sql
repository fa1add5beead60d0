-- Scenes converted at upload (USD, issue #41): the uploaded source's hash and file name, so a
-- job's EXR names what the user submitted as well as the glTF the workers rendered. Removed
-- with its scene.
CREATE TABLE scene_sources (
    sha256          text PRIMARY KEY REFERENCES scenes (sha256) ON DELETE CASCADE,
    source_format   text NOT NULL,
    source_sha256   text NOT NULL,
    source_filename text NOT NULL
);
