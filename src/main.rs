//! `doorslam`: the one binary of the system (services, offline tools, demo).

fn main() -> std::process::ExitCode {
    doorslam::cli::main()
}
