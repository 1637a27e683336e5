-- radiance schema 3: bake jobs (a trained model becomes splats). Schema 1's
-- check on a job's kind knew training, video and pose jobs only, so a bake
-- job could not be queued in a distributed deployment. Widening the check
-- is additive: rows of the older kinds stay valid.
ALTER TABLE jobs DROP CONSTRAINT jobs_kind_check;
ALTER TABLE jobs ADD CONSTRAINT jobs_kind_check CHECK (kind IN ('train', 'video', 'poses', 'bake'));
