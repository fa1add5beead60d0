-- API tokens of clients (stored as the SHA-256 of the token, never the token) and the owner of
-- each job: the name of the token that submitted it ('' for jobs of a farm without tokens).
CREATE TABLE api_tokens (
    id          text PRIMARY KEY,
    name        text NOT NULL CHECK (name <> ''),
    sha256      text NOT NULL UNIQUE CHECK (sha256 ~ '^[0-9a-f]{64}$'),
    admin       boolean NOT NULL DEFAULT false,
    created_at  timestamptz NOT NULL DEFAULT now(),
    revoked_at  timestamptz
);
-- A name belongs to one live token at a time; a revoked token's name may be given to a new one
-- (rotation: the new token owns the old one's jobs).
CREATE UNIQUE INDEX api_tokens_live_name ON api_tokens (name) WHERE revoked_at IS NULL;

ALTER TABLE jobs ADD COLUMN owner text NOT NULL DEFAULT '';
CREATE INDEX jobs_owner_created ON jobs (owner, created_at DESC, id DESC);
