//! A worker that stops cleanly gives its job back; one that was frozen
//! past its lease finds the job taken and writes nothing more for it.

use std::time::{Duration, Instant, SystemTime};

use serde_json::json;

use crate::cluster::{Cluster, Node, serial};
use crate::common::Svc;

/// A job that never ends by itself (the tests cancel it).
const ENDLESS: u64 = 1_000_000;

/// `job_runs` of job `id`: (attempt, worker, outcome), in order.
async fn runs(sql: &tokio_postgres::Client, id: &str) -> Vec<(i32, String, Option<String>)> {
    let rows = sql
        .query("SELECT attempt, worker_id, outcome FROM job_runs WHERE job_id = $1 ORDER BY attempt", &[&id])
        .await
        .unwrap();
    rows.iter().map(|r| (r.get(0), r.get(1), r.get(2))).collect()
}

/// The step `node` resumed job `id` from, per its log.
fn resumed_at(node: &Node, id: &str) -> Option<u64> {
    let log = node.log();
    let line = log.lines().find(|l| l.contains("resuming from checkpoint") && l.contains(id))?;
    line.split("step=").nth(1)?.split_whitespace().next()?.parse().ok()
}

/// Waits up to `secs` for `pred` over the node's log.
async fn wait_log(node: &Node, secs: u64, pred: impl Fn(&str) -> bool) {
    let t0 = Instant::now();
    while !pred(&node.log()) {
        assert!(t0.elapsed() < Duration::from_secs(secs), "{}'s log did not show it:\n{}", node.name, node.log());
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sigterm_requeues_the_job_and_another_worker_resumes_it() {
    let _serial = serial().await;
    let cluster = Cluster::start().await;
    let api = cluster.node("api", "api-1", &[]);
    let mut first = cluster.node("worker", "worker-1", &[]);
    let svc = Svc::remote(api.base.clone());
    let scene = svc.upload_ball().await;
    let id = svc.job(&scene, json!({ "steps": ENDLESS })).await;
    svc.wait_job(&id, 60.0, |v| v["status"] == "running" && v["progress"]["step"].as_u64() >= Some(10)).await;
    let seen = svc.wait_job(&id, 60.0, |v| v["model_id"].is_string()).await;

    let stopped = Instant::now();
    let status = first.terminate(Duration::from_secs(30));
    assert!(status.success(), "{status}");
    eprintln!("worker-1 exited {:.2} s after SIGTERM", stopped.elapsed().as_secs_f64());
    let (_, job) = svc.get(&format!("/v1/jobs/{id}")).await;
    assert_eq!((job["status"].as_str(), job["crashes"].as_u64()), (Some("queued"), Some(0)), "{job}");
    let sql = cluster.sql().await;
    assert_eq!(runs(&sql, &id).await, vec![(1, "worker-1".into(), Some("interrupted".into()))]);

    let second = cluster.node("worker", "worker-2", &[]);
    svc.wait_job(&id, 60.0, |v| v["status"] == "running" && v["attempts"] == 2).await;
    wait_log(&second, 30, |log| log.contains("resuming from checkpoint")).await;
    let from = resumed_at(&second, &id).expect("resumed");
    assert!(from >= seen["progress"]["step"].as_u64().unwrap(), "resumed at {from}, the job had reached {seen}");
    let (s, v) = svc.post_json(&format!("/v1/jobs/{id}/cancel"), json!({})).await;
    assert!(s.is_success(), "{v}");
    let done = svc.wait_job(&id, 60.0, |v| v["status"] != "running").await;
    assert_eq!(done["status"], "canceled", "{done}");
    assert_eq!(
        runs(&sql, &id).await,
        vec![(1, "worker-1".into(), Some("interrupted".into())), (2, "worker-2".into(), Some("canceled".into()))]
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_worker_frozen_past_its_lease_fences_itself_and_writes_nothing() {
    let _serial = serial().await;
    let cluster = Cluster::start().await;
    let api = cluster.node("api", "api-1", &[]);
    let frozen = cluster.node("worker", "worker-1", &[]);
    let svc = Svc::remote(api.base.clone());
    let scene = svc.upload_ball().await;
    let id = svc.job(&scene, json!({ "steps": ENDLESS })).await;
    svc.wait_job(&id, 60.0, |v| v["status"] == "running" && v["model_id"].is_string()).await;
    let other = cluster.node("worker", "worker-2", &[]);

    // Frozen past its lease: the other worker takes the job over (about a
    // lease after the last renewal).
    let pid = frozen.child.id() as i32;
    let froze = Instant::now();
    unsafe { libc::kill(pid, libc::SIGSTOP) };
    let sql = cluster.sql().await;
    let row = sql.query_one("SELECT lease_expires_at FROM jobs WHERE id = $1", &[&id]).await.unwrap();
    let expiry: SystemTime = row.get(0);
    let taken = svc.wait_job(&id, 60.0, |v| v["status"] == "running" && v["attempts"] == 2).await;
    eprintln!("taken over {:.1} s after the freeze", froze.elapsed().as_secs_f64());
    let row = sql.query_one("SELECT claimed_at FROM job_runs WHERE job_id = $1 AND attempt = 2", &[&id]).await.unwrap();
    let claimed: SystemTime = row.get(0);
    assert!(claimed > expiry, "claimed again before the frozen worker's lease expired");
    let owner: String = sql.query_one("SELECT lease_owner FROM jobs WHERE id = $1", &[&id]).await.unwrap().get(0);
    assert_eq!(owner, "worker-2", "{taken}");
    unsafe { libc::kill(pid, libc::SIGCONT) };

    // Thawed, it sees it may have lost the lease and stops the job; the
    // job stays the other worker's, its lost run as the reclaim closed it.
    wait_log(&frozen, 60, |log| log.contains("writing nothing more for it")).await;
    wait_log(&frozen, 60, |log| log.contains("is not recorded: its lease is lost")).await;
    let (_, job) = svc.get(&format!("/v1/jobs/{id}")).await;
    assert_eq!((job["status"].as_str(), job["attempts"].as_u64()), (Some("running"), Some(2)), "{job}");
    assert_eq!(frozen.metric("radiance_worker_leases_lost_total").await, 1.0);
    assert_eq!(other.metric("radiance_jobs_reclaimed_total").await, 1.0);
    let row = sql.query_one("SELECT lease_owner FROM jobs WHERE id = $1", &[&id]).await.unwrap();
    assert_eq!(row.get::<_, String>(0), "worker-2");
    assert_eq!(runs(&sql, &id).await, vec![(1, "worker-1".into(), Some("lost".into())), (2, "worker-2".into(), None)]);

    let (s, v) = svc.post_json(&format!("/v1/jobs/{id}/cancel"), json!({})).await;
    assert!(s.is_success(), "{v}");
    let done = svc.wait_job(&id, 60.0, |v| v["status"] != "running").await;
    assert_eq!(done["status"], "canceled", "{done}");
    let ran = runs(&sql, &id).await;
    assert_eq!(ran, vec![(1, "worker-1".into(), Some("lost".into())), (2, "worker-2".into(), Some("canceled".into()))]);
    drop((frozen, other));
}
