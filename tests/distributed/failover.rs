//! A worker killed mid-training: its job finishes on the other worker,
//! resumed from its last checkpoint, and no job runs on two workers at once.

use std::collections::HashMap;
use std::time::{Duration, Instant, SystemTime};

use serde_json::json;

use crate::cluster::{Backend, Cluster, LEASE_SECONDS, serial};
use crate::common::Svc;

/// Steps of each job: long enough that the first is still training when
/// its worker is killed.
const STEPS: u64 = 300;

/// One `job_runs` row.
#[derive(Debug)]
struct RunRow {
    attempt: i32,
    worker: String,
    claimed_at: SystemTime,
    ended_at: Option<SystemTime>,
    outcome: Option<String>,
}

async fn runs(sql: &tokio_postgres::Client) -> HashMap<String, Vec<RunRow>> {
    let rows = sql
        .query(
            "SELECT job_id, attempt, worker_id, claimed_at, ended_at, outcome FROM job_runs ORDER BY job_id, attempt",
            &[],
        )
        .await
        .unwrap();
    let mut by_job: HashMap<String, Vec<RunRow>> = HashMap::new();
    for r in rows {
        by_job.entry(r.get(0)).or_default().push(RunRow {
            attempt: r.get(1),
            worker: r.get(2),
            claimed_at: r.get(3),
            ended_at: r.get(4),
            outcome: r.get(5),
        });
    }
    by_job
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_killed_workers_job_resumes_on_the_other_from_its_checkpoint() {
    a_killed_workers_job_resumes_on_the_other_from_its_checkpoint_on(Backend::File).await;
}

/// The same over a real S3 server: checkpoints, scenes and videos go
/// through S3 (one PUT or a multipart upload by size, listings, reads).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_killed_workers_job_resumes_on_the_other_from_its_checkpoint_on_s3() {
    a_killed_workers_job_resumes_on_the_other_from_its_checkpoint_on(Backend::S3).await;
}

/// The kill -9 of a worker mid-training, with the objects kept by `backend`.
async fn a_killed_workers_job_resumes_on_the_other_from_its_checkpoint_on(backend: Backend) {
    let _serial = serial().await;
    let t0 = Instant::now();
    let cluster = Cluster::start_on(backend).await;
    let api = cluster.node("api", "api-1", &[]);
    let mut workers = [cluster.node("worker", "worker-1", &[]), cluster.node("worker", "worker-2", &[])];
    eprintln!("cluster up in {:.1} s", t0.elapsed().as_secs_f64());
    let svc = Svc::remote(api.base.clone());
    let scene = svc.upload_ball().await;
    let mut jobs = Vec::new();
    for _ in 0..5 {
        jobs.push(svc.job(&scene, json!({ "steps": STEPS })).await);
    }

    // The first job seen with a checkpoint mid-training: freeze its worker
    // (SIGSTOP), so the job cannot move on while the test looks, check it
    // is still mid-training under that worker's lease, and kill the worker.
    // A job that moved on before the freeze (this thread was starved) is
    // let go (SIGCONT), and the search goes on.
    let sql = cluster.sql().await;
    let deadline = Instant::now() + Duration::from_secs(120);
    let state = "SELECT status, lease_owner, lease_expires_at, model_id IS NOT NULL,
                        COALESCE((progress->>'step')::bigint, 0) FROM jobs WHERE id = $1";
    let mid_training = |status: &str, has_model: bool, step: i64| {
        status == "running" && has_model && (10..STEPS as i64 / 2).contains(&step)
    };
    let (victim, owner, index, expiry_before_kill, step) = 'search: loop {
        assert!(Instant::now() < deadline, "no job saved a checkpoint mid-training within 120 s");
        for id in &jobs {
            let row = sql.query_one(state, &[id]).await.unwrap();
            let (status, owner): (String, Option<String>) = (row.get(0), row.get(1));
            let Some(owner) = owner.filter(|_| mid_training(status.as_str(), row.get(3), row.get(4))) else { continue };
            let index = workers.iter().position(|w| w.name == owner).expect("the job's worker is one of ours");
            let pid = workers[index].child.id() as i32;
            unsafe { libc::kill(pid, libc::SIGSTOP) };
            let row = sql.query_one(state, &[id]).await.unwrap();
            let (status, still): (String, Option<String>) = (row.get(0), row.get(1));
            let step: i64 = row.get(4);
            if still.as_deref() == Some(owner.as_str()) && mid_training(status.as_str(), row.get(3), step) {
                break 'search (id.clone(), owner, index, row.get::<_, SystemTime>(2), step);
            }
            unsafe { libc::kill(pid, libc::SIGCONT) };
            eprintln!("{id} moved on ({status}, step {step}) before {owner} was frozen; looking again");
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    };
    let killed_at = Instant::now();
    workers[index].kill9();
    eprintln!("killed {owner} running {victim} at step {step} ({:.1} s in)", t0.elapsed().as_secs_f64());
    let survivor = &workers[1 - index];

    // It comes back on the other worker and every job succeeds.
    let resumed = svc.wait_job(&victim, 120.0, |v| v["status"] == "running" && v["attempts"] == 2).await;
    eprintln!("{victim} running again {:.1} s after the kill", killed_at.elapsed().as_secs_f64());
    assert_eq!(resumed["crashes"], 1, "{resumed}");
    for id in &jobs {
        let done = svc.wait_job(id, 300.0, |v| v["status"] != "queued" && v["status"] != "running").await;
        assert_eq!(done["status"], "succeeded", "{done}");
        let model = done["model_id"].as_str().unwrap();
        let (_, m) = svc.get(&format!("/v1/models/{model}")).await;
        assert_eq!(m["steps"], STEPS, "{m}");
        assert_eq!(m["complete"], true, "{m}");
    }
    eprintln!("all five succeeded {:.1} s in", t0.elapsed().as_secs_f64());
    let (_, done) = svc.get(&format!("/v1/jobs/{victim}")).await;
    assert_eq!((done["attempts"].as_u64(), done["crashes"].as_u64()), (Some(2), Some(1)), "{done}");

    // The survivor took it back (API nodes never reclaim).
    assert_eq!(survivor.metric("radiance_jobs_reclaimed_total").await, 1.0);
    // The survivor resumed it from the checkpoint, not from scratch.
    let log = survivor.log();
    let resume_line = log
        .lines()
        .find(|l| l.contains("resuming from checkpoint") && l.contains(victim.as_str()))
        .unwrap_or_else(|| panic!("{} did not resume {victim} from a checkpoint:\n{log}", survivor.name));
    let step: u64 =
        resume_line.split("step=").nth(1).and_then(|s| s.split_whitespace().next()).unwrap().parse().unwrap();
    assert!(step > 0 && step < STEPS, "{resume_line}");

    // The runs: the lost one, then the succeeded one on the other worker,
    // claimed after the first lease expired; every other job ran once; no
    // two runs of a job, nor two of a worker (one job at a time), overlap.
    let runs = runs(&sql).await;
    assert_eq!(runs.len(), 5, "{runs:?}");
    let v = &runs[&victim];
    assert_eq!(v.len(), 2, "{v:?}");
    assert_eq!((v[0].attempt, v[0].worker.as_str(), v[0].outcome.as_deref()), (1, owner.as_str(), Some("lost")));
    assert_eq!((v[1].attempt, v[1].worker.as_str()), (2, survivor.name.as_str()));
    assert_eq!(v[1].outcome.as_deref(), Some("succeeded"));
    assert!(v[1].claimed_at > expiry_before_kill, "claimed again before the lost lease expired: {v:?}");
    assert!(v[1].claimed_at >= v[0].ended_at.unwrap(), "{v:?}");
    let lease = Duration::from_secs(LEASE_SECONDS);
    let takeover = v[1].claimed_at.duration_since(expiry_before_kill - lease).unwrap_or_default();
    eprintln!("second claim {:.1} s after the last renewal before the kill", takeover.as_secs_f64());
    let mut by_worker: HashMap<&str, Vec<&RunRow>> = HashMap::new();
    for (id, rs) in &runs {
        if *id != victim {
            assert_eq!(rs.len(), 1, "{id}: {rs:?}");
            assert_eq!(rs[0].outcome.as_deref(), Some("succeeded"), "{id}: {rs:?}");
        }
        for r in rs {
            by_worker.entry(r.worker.as_str()).or_default().push(r);
        }
    }
    for rs in runs.values() {
        no_overlap(&rs.iter().collect::<Vec<_>>());
    }
    for (_, mut rs) in by_worker {
        rs.sort_by_key(|r| r.claimed_at);
        no_overlap(&rs);
    }
    eprintln!("test done in {:.1} s", t0.elapsed().as_secs_f64());
    drop(api);
}

/// No run starts before the one before it ended.
fn no_overlap(runs: &[&RunRow]) {
    for w in runs.windows(2) {
        let ended = w[0].ended_at.expect("every run has ended");
        assert!(w[1].claimed_at >= ended, "runs overlap: {:?} and {:?}", w[0], w[1]);
    }
}
