use clap::Parser;

fn main() {
    tune_malloc();
    let cli = radiance::cli::Cli::parse();
    if let Err(e) = radiance::cli::run(cli) {
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
}

/// Keeps glibc's allocator from handing large blocks back to the kernel
/// and faulting them in again. A bake allocates and frees a few buffers of
/// megabytes every step (a view's projections, tile lists, per-entry
/// gradients); whether glibc serves them from its heap or maps them afresh
/// depends on its adaptive threshold, so on what the process freed before.
/// After training in the same process (`bench --bake`, a worker's jobs),
/// every step mapped them anew: in `radiance bench --data fox --budgets 30
/// --bake 20 --threads 2` the bake made 151 steps and the run 936k page
/// faults, against 180 steps and 83k with the thresholds fixed as here
/// (the 2-core Xeon VM; `radiance bake` alone: 189-193 steps, 60-69k).
/// Blocks up to 32 MiB (glibc's largest threshold) come from the heap, and
/// up to 256 MiB of free heap is kept for the next step. The price is a
/// fragmented heap in training, which the memory estimate counts
/// (`engine::train::estimate`).
fn tune_malloc() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: mallopt only sets the allocator's parameters; it is called
    // before any other thread exists.
    unsafe {
        libc::mallopt(libc::M_MMAP_THRESHOLD, 32 << 20);
        libc::mallopt(libc::M_TRIM_THRESHOLD, 256 << 20);
    }
}
