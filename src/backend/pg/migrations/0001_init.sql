-- radiance schema 1: the job queue and the records of scenes, models and
-- videos (docs/design/scale-out.md, section 2.3). Applied once, in one
-- transaction, by `store::pg::migrate`; never edit it once released (its
-- sha256 is recorded and checked): change the schema in a new, additive
-- migration.
--
-- Timestamps shown to clients stay bigint milliseconds since the epoch, as
-- in the records today; leases and run history use the database clock
-- (timestamptz, now()), so no node's clock decides who owns a job.

-- Milliseconds since the epoch by the database clock (the moment of the
-- call, not the transaction's start).
CREATE FUNCTION radiance_now_ms() RETURNS bigint LANGUAGE sql VOLATILE AS
  $$ SELECT (extract(epoch FROM clock_timestamp()) * 1000)::bigint $$;

-- storage::SceneInfo in `record`; `status` and `created_at` copied out of it
-- for the checks and the order of listings.
CREATE TABLE scenes (
  id text PRIMARY KEY,
  status text NOT NULL CHECK (status IN ('ready', 'posing', 'failed')),
  created_at bigint NOT NULL,
  record jsonb NOT NULL
);
CREATE INDEX scenes_order ON scenes (created_at, id);

-- A job (jobs::Job): its columns plus `spec` (the JobSpec, tagged by kind)
-- and `progress` (the JobProgress) rebuild the JSON clients see.
CREATE TABLE jobs (
  id text PRIMARY KEY,
  seq bigint GENERATED ALWAYS AS IDENTITY UNIQUE,      -- enqueue order (Job::seq)
  kind text NOT NULL CHECK (kind IN ('train', 'video', 'poses')),
  status text NOT NULL CHECK (status IN ('queued', 'running', 'succeeded', 'failed', 'canceled')),
  spec jsonb NOT NULL CHECK (spec->>'kind' = kind),
  scene_id text,                                       -- train, poses
  target_model_id text,   -- train: the model it writes (reserved_model_id); video: the model it renders
  model_id text,                                       -- Job::model_id as clients see it
  video_id text,                                       -- Job::video_id
  created_at bigint NOT NULL,
  started_at bigint,
  finished_at bigint,
  error text,
  progress jsonb NOT NULL,                             -- no default: JobProgress has required fields
  attempts int NOT NULL DEFAULT 0 CHECK (attempts >= 0),
  crashes int NOT NULL DEFAULT 0 CHECK (crashes >= 0),
  memory_estimate_bytes bigint NOT NULL DEFAULT 0 CHECK (memory_estimate_bytes >= 0),
  cancel_requested boolean NOT NULL DEFAULT false,
  -- The lease of the worker running it: all three or none, and only while running.
  lease_owner text,
  lease_token uuid,
  lease_expires_at timestamptz,
  CHECK ((status = 'running') = (lease_token IS NOT NULL)),
  CHECK ((lease_token IS NULL) = (lease_owner IS NULL)),
  CHECK ((lease_token IS NULL) = (lease_expires_at IS NULL))
) WITH (fillfactor = 70);  -- heartbeats change only unindexed columns: HOT updates
CREATE INDEX jobs_queued ON jobs (seq) WHERE status = 'queued';
CREATE INDEX jobs_status_seq ON jobs (status, seq);
CREATE INDEX jobs_active_scene ON jobs (scene_id) WHERE status IN ('queued', 'running');
CREATE INDEX jobs_active_model ON jobs (target_model_id) WHERE status IN ('queued', 'running');

-- One row per claim: the history of a job's runs, the evidence that no job
-- ran twice at once, and what metrics count.
CREATE TABLE job_runs (
  job_id text NOT NULL REFERENCES jobs ON DELETE CASCADE,
  attempt int NOT NULL,
  worker_id text NOT NULL,
  claimed_at timestamptz NOT NULL DEFAULT now(),
  ended_at timestamptz,
  outcome text CHECK (outcome IN ('succeeded', 'failed', 'canceled', 'interrupted', 'lost')),
  PRIMARY KEY (job_id, attempt)
);

-- storage::ModelInfo in `record`; its checkpoint is the object
-- models/ID/<checkpoint_sha256>.ckpt. `saved_at` (database clock) tells
-- crash counting whether a run saved progress after it was claimed.
CREATE TABLE models (
  id text PRIMARY KEY,
  scene_id text NOT NULL,
  job_id text NOT NULL,
  created_at bigint NOT NULL,
  updated_at bigint NOT NULL,
  checkpoint_sha256 text NOT NULL,
  saved_at timestamptz NOT NULL DEFAULT now(),
  record jsonb NOT NULL
);
CREATE INDEX models_order ON models (created_at, id);

-- storage::VideoInfo in `record`.
CREATE TABLE videos (
  id text PRIMARY KEY,
  model_id text NOT NULL,
  job_id text NOT NULL,
  created_at bigint NOT NULL,
  record jsonb NOT NULL
);
CREATE INDEX videos_order ON videos (created_at, id);

-- Nodes that run jobs, and what they can take.
CREATE TABLE workers (
  id text PRIMARY KEY,
  host text NOT NULL,
  pid int NOT NULL,
  role text NOT NULL,
  version text NOT NULL,
  colmap boolean NOT NULL,
  max_concurrent int NOT NULL,
  memory_budget_bytes bigint NOT NULL,
  started_at timestamptz NOT NULL DEFAULT now(),
  last_seen_at timestamptz NOT NULL DEFAULT now()
);

-- One holder at a time per maintenance task.
CREATE TABLE maintenance (name text PRIMARY KEY, holder text, lease_expires_at timestamptz);
INSERT INTO maintenance (name) VALUES ('sweep'), ('orphans');

-- Every change of a job is announced on one channel, payload
-- "<event>:<job id>": `queued` (a job became claimable), `cancel` (a
-- running job was asked to stop), `job` (anything else). NOTIFY is
-- delivered at commit, duplicates within a transaction folded; listeners
-- take it as a hint and read the row.
CREATE FUNCTION radiance_notify_job() RETURNS trigger LANGUAGE plpgsql AS $$
BEGIN
  PERFORM pg_notify('radiance', CASE
    WHEN NEW.status = 'queued' AND (TG_OP = 'INSERT' OR OLD.status <> 'queued') THEN 'queued:'
    WHEN TG_OP = 'UPDATE' AND NEW.cancel_requested AND NOT OLD.cancel_requested THEN 'cancel:'
    ELSE 'job:' END || NEW.id);
  RETURN NULL;
END $$;
CREATE TRIGGER jobs_notify AFTER INSERT OR UPDATE ON jobs
  FOR EACH ROW EXECUTE FUNCTION radiance_notify_job();
