-- radiance schema 2: radiance_now_ms() truncates to the millisecond, as the
-- embedded store's `storage::now_ms` does. Schema 1's cast to bigint
-- rounded, so a job's `created_at` could be up to half a millisecond ahead
-- of the clock a client reads just after the enqueue returned. Replacing
-- the function is additive: nodes of schema 1 call it unchanged.
CREATE OR REPLACE FUNCTION radiance_now_ms() RETURNS bigint LANGUAGE sql VOLATILE AS
  $$ SELECT floor(extract(epoch FROM clock_timestamp()) * 1000)::bigint $$;
