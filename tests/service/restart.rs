//! Restarts: queued jobs run and interrupted ones resume, also after `kill -9`.

use reqwest::StatusCode;
use serde_json::{Value, json};

use crate::common::*;

/// The interrupted jobs' budget, seconds of training: more than a stalled
/// test thread lets pass between seeing step 10 and the stop or kill.
const LONG_SECONDS: f64 = 20.0;

fn is_final(v: &Value) -> bool {
    ["succeeded", "failed", "canceled"].contains(&v["status"].as_str().unwrap_or(""))
}

/// The finished model `m` trained for its whole budget, over both lives.
fn assert_budget_spent(m: &Value) {
    assert_eq!(m["complete"], true, "{m}");
    assert!(m["training_seconds"].as_f64().unwrap() >= LONG_SECONDS, "{m}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn restart_runs_queued_jobs_and_resumes_interrupted_ones() {
    let data = tempfile::tempdir().unwrap();
    // First life: the scheduler is off, so the job only gets queued.
    let mut cfg = config(data.path());
    cfg.scheduler.run_jobs = false;
    let svc = Svc::start(cfg).await;
    let scene = svc.upload_ball().await;
    let queued = svc.job(&scene, json!({ "steps": 20 })).await;
    svc.stop().await;

    // Second life: it runs. Start a longer one and stop the server mid-training.
    let svc = Svc::start(config(data.path())).await;
    let (s, v) = svc.get(&format!("/v1/scenes/{scene}")).await;
    assert_eq!(s, StatusCode::OK, "{v}");
    let job = svc.wait_job(&queued, 60.0, |v| v["status"] == "succeeded").await;
    assert_eq!(job["progress"]["step"], 20);
    // A budget of training time (carried across restarts): the job cannot
    // end before the stop, however slow this test's thread or fast the machine.
    let long = svc.job(&scene, json!({ "seconds": LONG_SECONDS })).await;
    let seen =
        svc.wait_job(&long, 60.0, |v| v["model_id"].is_string() && v["progress"]["step"].as_u64() >= Some(10)).await;
    svc.stop().await;
    let store = radiance::datadir::DataDir::open(data.path()).unwrap();
    let on_disk: Value = store.get_job(&long).unwrap().expect("the job is recorded");
    drop(store);
    // Not final: a clean shutdown writes it back as queued (a job found
    // `running` at start-up was cut short by a crash, which is counted).
    assert_eq!(on_disk["status"], "queued", "an interrupted job is not final");
    assert_eq!(on_disk["crashes"], 0);

    // Third life: it resumes from its checkpoint and finishes.
    let svc = Svc::start(config(data.path())).await;
    let done = svc.wait_job(&long, 120.0, is_final).await;
    assert_eq!((done["status"].as_str(), done["attempts"].as_u64()), (Some("succeeded"), Some(2)), "{done}");
    let model = done["model_id"].as_str().unwrap();
    let (_, m) = svc.get(&format!("/v1/models/{model}")).await;
    assert_budget_spent(&m);
    // Past the checkpoint of the stop (at or after `seen`): trained on after it.
    assert!(m["steps"].as_u64().unwrap() > seen["progress"]["step"].as_u64().unwrap(), "{m}\n{seen}");
    let (_, all) = svc.get("/v1/jobs").await;
    assert_eq!(all.as_array().unwrap().len(), 2);
    svc.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn job_killed_mid_training_resumes_after_restart() {
    let data = tempfile::tempdir().unwrap();
    let (mut child, base) = spawn_binary(data.path());
    let svc = Svc::remote(base);
    let scene = svc.upload_ball().await;
    // A budget of training time, as above: the kill lands mid-training.
    let id = svc.job(&scene, json!({ "seconds": LONG_SECONDS })).await;
    svc.wait_job(&id, 60.0, |v| v["model_id"].is_string() && v["progress"]["step"].as_u64() >= Some(10)).await;
    child.kill().unwrap(); // SIGKILL: no chance to checkpoint or record anything
    child.wait().unwrap();

    let (mut child, base) = spawn_binary(data.path());
    let svc = Svc::remote(base);
    let done = svc.wait_job(&id, 120.0, is_final).await;
    assert_eq!(done["status"], "succeeded", "{done}");
    assert_eq!(done["attempts"], 2, "{done}");
    let (_, m) = svc.get(&format!("/v1/models/{}", done["model_id"].as_str().unwrap())).await;
    assert_budget_spent(&m);
    child.kill().unwrap();
    child.wait().unwrap();
}
