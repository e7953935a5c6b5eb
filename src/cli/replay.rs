//! `doorslam replay DATASET`: play a KITTI or EuRoC folder into the on-robot pipeline
//! (iceoryx2 frame service) at real time, faster, as fast as possible, or stepped; with
//! `--robots N`, one sequence plays N robots at once (consecutive parts, as in the
//! paper's KITTI 00 experiment), robot k publishing under robot id `<prefix><letter>`.

use std::path::PathBuf;

use anyhow::{Context, Result};
use clap::Args;
use doorslam_camera::ReplayConfig;

#[derive(Debug, Args)]
pub struct ReplayArgs {
    /// Dataset folder: KITTI (image_0/, image_1/, times.txt) or EuRoC ([mav0/]cam0/data).
    pub dataset: PathBuf,
    /// Robot id whose services receive the frames (single-robot mode).
    #[arg(long, default_value = "a")]
    pub robot: String,
    /// Index of that robot in the team (keys 'a' + index).
    #[arg(long, default_value_t = 0)]
    pub robot_index: u32,
    /// Split the sequence into N robots, played together (ids `<prefix>a`, `<prefix>b`, ...).
    #[arg(long)]
    pub robots: Option<usize>,
    /// Prefix of the robot ids in `--robots` mode.
    #[arg(long, default_value = "")]
    pub robot_prefix: String,
    /// 1 = real time, 2 = twice as fast, 0 = as fast as possible.
    #[arg(long, default_value_t = 1.0)]
    pub rate: f64,
    /// One frame per Enter on standard input.
    #[arg(long)]
    pub step: bool,
    /// Ground-truth poses (KITTI format) if not poses.txt inside the folder.
    #[arg(long)]
    pub truth: Option<PathBuf>,
    /// Seconds to wait for a subscriber before playing.
    #[arg(long, default_value_t = 10.0)]
    pub wait_s: f64,
}

pub fn run(args: ReplayArgs) -> Result<()> {
    let config = |split: Option<[usize; 2]>| ReplayConfig {
        path: args.dataset.clone(),
        rate: args.rate,
        truth: args.truth.clone(),
        split,
        wait_for_subscribers_s: args.wait_s,
        step: args.step,
        start_unix_ms: None,
        status_file: None,
    };
    anyhow::ensure!(
        args.rate.is_finite() && args.rate >= 0.0,
        "--rate {}: must be >= 0",
        args.rate
    );
    match args.robots {
        None => {
            let r = doorslam_camera::replay::run(&config(None), &args.robot, args.robot_index)
                .with_context(|| format!("replaying {}", args.dataset.display()))?;
            println!(
                "replayed {} frames of {} to robot {}",
                r.published,
                args.dataset.display(),
                args.robot
            );
        }
        Some(n) => {
            anyhow::ensure!((1..=26).contains(&n), "--robots {n}: must be 1..26");
            anyhow::ensure!(
                !args.step,
                "--step plays one robot at a time: use it without --robots"
            );
            let handles: Vec<_> = (0..n)
                .map(|k| {
                    let id = format!("{}{}", args.robot_prefix, (b'a' + k as u8) as char);
                    let c = config(Some([k, n]));
                    std::thread::spawn(move || {
                        doorslam_camera::replay::run(&c, &id, k as u32).map(|r| (id, r.published))
                    })
                })
                .collect();
            for h in handles {
                let (id, published) = h
                    .join()
                    .map_err(|_| anyhow::anyhow!("a replay thread panicked"))?
                    .with_context(|| format!("replaying {}", args.dataset.display()))?;
                println!("replayed {published} frames to robot {id}");
            }
        }
    }
    Ok(())
}
