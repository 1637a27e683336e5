//! The two "Scaling out" measurements of docs/benchmarks.md (issue 16,
//! docs/design/scale-out.md step 12), run by hand and printed as Markdown
//! tables:
//!
//! `cargo test --release --locked --test distributed bench -- --ignored --nocapture --test-threads 1`
//!
//! - `tiny_jobs_per_second`: how fast the queue hands out jobs that cost
//!   next to nothing to run (`steps: 1`), with 1, 2 and 4 worker processes;
//! - `death_to_resume`: how long a worker killed with SIGKILL keeps its job
//!   from moving, with leases of 5 s and 10 s.
//!
//! Both also check what they measure went right (every job succeeded once;
//! the killed job finished with its steps), so a figure never comes from a
//! broken run.

use std::time::{Duration, Instant, SystemTime};

use serde_json::json;

use crate::cluster::{Cluster, Node, serial};
use crate::common::Svc;

/// Jobs in each tiny-jobs run: enough for a rate, few enough that the
/// slowest run (one worker) stays well under a minute.
const TINY_JOBS: usize = 500;

/// `p` (0 to 1) of sorted `values`, nearest rank.
fn percentile(sorted: &[f64], p: f64) -> f64 {
    let rank = ((p * sorted.len() as f64).ceil() as usize).clamp(1, sorted.len());
    sorted[rank - 1]
}

/// Polls `sql` until `query` (one bigint) returns at least `want`; panics
/// after `secs`.
async fn wait_count(sql: &tokio_postgres::Client, query: &str, want: i64, secs: u64) {
    let deadline = Instant::now() + Duration::from_secs(secs);
    loop {
        let n: i64 = sql.query_one(query, &[]).await.unwrap().get(0);
        if n >= want {
            return;
        }
        assert!(Instant::now() < deadline, "{query}: {n} of {want} after {secs} s");
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

/// N `steps: 1` nerf-tiny jobs on the small test scene, one API node and
/// 1, 2 or 4 workers (`--threads 1` each): jobs/s from the first enqueue
/// to the last success (both from the database), and the p50/p95 of
/// `claimed_at - created_at`, which with all jobs enqueued at once is
/// mostly the time spent waiting behind the others.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[ignore = "a measurement, run by hand"]
async fn tiny_jobs_per_second() {
    let _serial = serial().await;
    let mut table = Vec::new();
    for workers in [1usize, 2, 4] {
        let cluster = Cluster::start().await;
        // The default refuses more than 100 queued jobs.
        let api = cluster.node("api", "api-1", &["--max-queued-jobs", "10000"]);
        let nodes: Vec<Node> = (1..=workers).map(|i| cluster.node("worker", &format!("worker-{i}"), &[])).collect();
        let svc = Svc::remote(api.base.clone());
        let scene = svc.upload_ball().await;
        let sql = cluster.sql().await;
        let started = Instant::now();
        for _ in 0..TINY_JOBS {
            svc.job(&scene, json!({ "steps": 1 })).await;
        }
        let enqueued = started.elapsed().as_secs_f64();
        let finals = "SELECT count(*) FROM jobs WHERE status IN ('succeeded', 'failed', 'canceled')";
        wait_count(&sql, finals, TINY_JOBS as i64, 300).await;

        // Every job succeeded, on its first and only run.
        let row = sql
            .query_one(
                "SELECT count(*) FILTER (WHERE status = 'succeeded' AND attempts = 1 AND crashes = 0),
                        count(*), min(created_at), max(finished_at)
                 FROM jobs",
                &[],
            )
            .await
            .unwrap();
        let (ok, all, first_created, last_finished): (i64, i64, i64, i64) =
            (row.get(0), row.get(1), row.get(2), row.get(3));
        assert_eq!((ok, all), (TINY_JOBS as i64, TINY_JOBS as i64), "every job succeeds once");
        let row = sql
            .query_one(
                "SELECT count(*), count(DISTINCT job_id), count(*) FILTER (WHERE outcome = 'succeeded'),
                        count(DISTINCT worker_id)
                 FROM job_runs",
                &[],
            )
            .await
            .unwrap();
        let (runs, jobs, succeeded, used): (i64, i64, i64, i64) = (row.get(0), row.get(1), row.get(2), row.get(3));
        assert_eq!((runs, jobs, succeeded), (TINY_JOBS as i64, TINY_JOBS as i64, TINY_JOBS as i64));

        let waits: Vec<f64> = sql
            .query(
                "SELECT (EXTRACT(EPOCH FROM r.claimed_at) * 1000 - j.created_at)::float8
                 FROM job_runs r JOIN jobs j ON j.id = r.job_id",
                &[],
            )
            .await
            .unwrap()
            .iter()
            .map(|r| r.get::<_, f64>(0) / 1000.0)
            .collect();
        let mut waits = waits;
        waits.sort_by(f64::total_cmp);
        let secs = (last_finished - first_created) as f64 / 1000.0;
        assert!(secs > 0.0, "the last success comes after the first enqueue");
        table.push(format!(
            "| {workers} | {TINY_JOBS} | {used} | {enqueued:.2} s | {secs:.2} s | {:.1} | {:.2} s | {:.2} s |",
            TINY_JOBS as f64 / secs,
            percentile(&waits, 0.5),
            percentile(&waits, 0.95),
        ));
        eprintln!("{}", table.last().unwrap());
        drop(nodes);
        drop(api);
    }
    println!(
        "Tiny jobs (nerf-tiny, `steps: 1`, 256 rays), one API node, workers with `--threads 1`, all jobs \
         enqueued at once over HTTP. On 2 cores, 4 worker processes (plus the API node and PostgreSQL) are \
         CPU-bound: more workers cannot go faster than the cores.\n"
    );
    println!(
        "| workers | jobs | workers used | enqueue time | first enqueue → last success | jobs/s | \
         claimed − created p50 | p95 |\n| --- | --- | --- | --- | --- | --- | --- | --- |"
    );
    for row in table {
        println!("{row}");
    }
}

/// Steps of the job killed mid-training: long enough that it is still
/// training when its worker dies, and that it visibly moves after resuming.
const LONG_STEPS: u64 = 1500;

/// When the killed job's step counter moved again, and to which step.
struct Sample {
    at: SystemTime,
    step: u64,
}

/// The times of one kill, in seconds after it.
struct Resume {
    queued: f64,
    running: f64,
    progress: f64,
}

/// One API node, two workers with `lease_seconds`, one training job: its
/// worker is killed (SIGKILL) once the job has a checkpoint, and the times
/// from the kill to the job back in `queued` (the lost run's end, written
/// by the reclaim), to `running` on the other worker (the second run's
/// claim) and to its first progress past the checkpoint it resumed from
/// (as clients see it: written by the heartbeats, at most a second apart).
///
/// The checkpoint is seen in the progress a heartbeat just wrote, so the
/// kill waits `phase` more: the kills of a series fall at different points
/// of the heartbeat (and reclaim) second, not all right after a renewal.
async fn one_kill(lease_seconds: u64, phase: Duration) -> Resume {
    let cluster = Cluster::start().await;
    let api = cluster.node("api", "api-1", &[]);
    let mut workers = [
        cluster.node_with_lease("worker", "worker-1", lease_seconds, &[]),
        cluster.node_with_lease("worker", "worker-2", lease_seconds, &[]),
    ];
    let svc = Svc::remote(api.base.clone());
    let scene = svc.upload_ball().await;
    let id = svc.job(&scene, json!({ "steps": LONG_STEPS })).await;
    let sql = cluster.sql().await;
    let state = "SELECT status, model_id IS NOT NULL, lease_owner, attempts, COALESCE((progress->>'step')::bigint, 0)
                 FROM jobs WHERE id = $1";

    // Kill its worker once a checkpoint is published, early in training.
    let deadline = Instant::now() + Duration::from_secs(120);
    let owner = loop {
        let r = sql.query_one(state, &[&id]).await.unwrap();
        let (status, saved, step): (String, bool, i64) = (r.get(0), r.get(1), r.get(4));
        if status == "running" && saved && step >= 10 {
            assert!(step < LONG_STEPS as i64 / 2, "the job ran too far before its first checkpoint: {step}");
            break r.get::<_, String>(2);
        }
        assert!(Instant::now() < deadline, "no checkpoint within 120 s ({status}, step {step})");
        tokio::time::sleep(Duration::from_millis(25)).await;
    };
    let index = workers.iter().position(|w| w.name == owner).expect("the job's worker is one of ours");
    tokio::time::sleep(phase).await;
    let killed_at = SystemTime::now();
    workers[index].kill9();
    let survivor = &workers[1 - index];

    // Sample the job's row until the resumed run's step moves: differs from
    // the last one the killed run wrote and passes the checkpoint it resumed
    // from (the survivor's log says which).
    let resumed_from = |log: &str| -> Option<u64> {
        let line = log.lines().find(|l| l.contains("resuming from checkpoint") && l.contains(id.as_str()))?;
        line.split("step=").nth(1).and_then(|s| s.split_whitespace().next()).and_then(|s| s.parse().ok())
    };
    let at_kill: i64 = sql.query_one(state, &[&id]).await.unwrap().get(4);
    let deadline = Instant::now() + Duration::from_secs(lease_seconds + 60);
    let (from, moved) = loop {
        let r = sql.query_one(state, &[&id]).await.unwrap();
        let (status, attempts, step): (String, i32, i64) = (r.get(0), r.get(3), r.get(4));
        let at = SystemTime::now();
        if attempts == 2
            && step != at_kill
            && let Some(from) = resumed_from(&survivor.log()).filter(|from| step as u64 > *from)
        {
            break (from, Sample { at, step: step as u64 });
        }
        assert!(status == "queued" || status == "running", "the job ended before it moved again: {status}");
        let waited = Instant::now() < deadline;
        assert!(waited, "not moving again within {} s of the kill ({status})", lease_seconds + 60);
        tokio::time::sleep(Duration::from_millis(25)).await;
    };
    let done = svc.wait_job(&id, 600.0, |v| v["status"] != "queued" && v["status"] != "running").await;
    assert_eq!(done["status"], "succeeded", "{done}");
    assert_eq!((done["attempts"].as_u64(), done["crashes"].as_u64()), (Some(2), Some(1)), "{done}");
    let (_, m) = svc.get(&format!("/v1/models/{}", done["model_id"].as_str().unwrap())).await;
    assert_eq!((&m["steps"], &m["complete"]), (&json!(LONG_STEPS), &json!(true)), "{m}");
    assert!(from > 0 && from < LONG_STEPS, "resumed from step {from}");

    // The runs' times.
    let runs = sql
        .query(
            "SELECT attempt, worker_id, ended_at, claimed_at, outcome FROM job_runs WHERE job_id = $1 ORDER BY attempt",
            &[&id],
        )
        .await
        .unwrap();
    assert_eq!(runs.len(), 2);
    let (lost_worker, lost_end, lost_outcome): (String, SystemTime, String) =
        (runs[0].get(1), runs[0].get(2), runs[0].get(4));
    let (second_worker, second_claim): (String, SystemTime) = (runs[1].get(1), runs[1].get(3));
    assert_eq!((lost_worker.as_str(), lost_outcome.as_str()), (owner.as_str(), "lost"));
    assert_eq!(second_worker, survivor.name);
    let after = |t: SystemTime| t.duration_since(killed_at).unwrap_or_default().as_secs_f64();
    let r = Resume { queued: after(lost_end), running: after(second_claim), progress: after(moved.at) };
    eprintln!(
        "lease {lease_seconds} s: killed {owner}; queued after {:.2} s, running on {} after {:.2} s, \
         step {} (resumed from {from}) after {:.2} s",
        r.queued, survivor.name, r.running, moved.step, r.progress
    );
    drop(workers);
    drop(api);
    r
}

/// `death_to_resume`'s repetitions per lease.
const REPETITIONS: usize = 3;

/// Min / median / max of `values`, in seconds.
fn spread(mut values: Vec<f64>) -> String {
    values.sort_by(f64::total_cmp);
    format!("{:.2} / {:.2} / {:.2} s", values[0], values[values.len() / 2], values[values.len() - 1])
}

/// A worker's death to its job resuming elsewhere, with leases of 5 s and
/// 10 s, [`REPETITIONS`] kills each ([`one_kill`]).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[ignore = "a measurement, run by hand"]
async fn death_to_resume() {
    let _serial = serial().await;
    let mut table = Vec::new();
    for lease in [5, 10] {
        let mut kills = Vec::new();
        for k in 0..REPETITIONS {
            let phase = Duration::from_secs_f64(k as f64 / REPETITIONS as f64);
            kills.push(one_kill(lease, phase).await);
        }
        table.push(format!(
            "| {lease} s | {REPETITIONS} | {} | {} | {} |",
            spread(kills.iter().map(|k| k.queued).collect()),
            spread(kills.iter().map(|k| k.running).collect()),
            spread(kills.iter().map(|k| k.progress).collect()),
        ));
    }
    println!(
        "Death to resume: one API node, two workers (`--threads 1`), a nerf-tiny job of {LONG_STEPS} steps \
         with checkpoints every 0.2 s; its worker killed with SIGKILL once it has a checkpoint, the k-th kill \
         k/{REPETITIONS} s after a heartbeat (k from 0). Times after the kill, min / median / max; progress \
         is what clients see (heartbeats write it, at most 1 s apart).\n"
    );
    println!(
        "| lease | kills | → `queued` (reclaimed) | → `running` on the other worker | → first progress after \
         resuming |\n| --- | --- | --- | --- | --- |"
    );
    for row in table {
        println!("{row}");
    }
}
