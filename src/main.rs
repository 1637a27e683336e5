use clap::Parser;

fn main() {
    let cli = radiance::cli::Cli::parse();
    if let Err(e) = radiance::cli::run(cli) {
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
}
