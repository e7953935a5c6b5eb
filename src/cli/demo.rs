//! `doorslam demo`: until the end-to-end SLAM demo exists (next wave), the demo is a
//! check of the whole dependency stack on real data, each step using the real library
//! the way the services will: OpenCV features on a EuRoC stereo pair, the pair through
//! iceoryx2 shared memory, a descriptor head in onnxruntime, the descriptor between two
//! Zenoh peers on loopback, and a sparse Cholesky solve with faer. No step here is SLAM,
//! and nothing here is reported as visual odometry.

use std::path::PathBuf;
use std::time::{Duration, Instant};

use anyhow::{bail, ensure, Context, Result};
use clap::Args;
use doorslam_frontend::opencv::prelude::*;
use doorslam_team::zenoh::Wait;

#[derive(Debug, Args)]
pub struct DemoArgs {
    /// The shared data folder (default: $DOORSLAM_DATA, else ../shared/data).
    #[arg(long)]
    pub data: Option<PathBuf>,
}

fn step(name: &str, detail: String, t: Instant) {
    println!(
        "  ok  {name:<14} {detail} ({:.1} ms)",
        t.elapsed().as_secs_f64() * 1e3
    );
}

pub fn run(args: DemoArgs) -> Result<()> {
    let data = args
        .data
        .or_else(|| std::env::var_os("DOORSLAM_DATA").map(PathBuf::from))
        .unwrap_or_else(|| PathBuf::from("../shared/data"));
    let pair = data.join("stereo/euroc_loop_closure_pairs");
    ensure!(
        pair.is_dir(),
        "data folder {} not found: pass --data or set DOORSLAM_DATA",
        pair.display()
    );
    println!("doorslam demo: dependency-stack check on real data (the SLAM demo arrives with the end-to-end issue)");

    // OpenCV: the front-end's feature detector on a real EuRoC frame.
    let t = Instant::now();
    let left = doorslam_frontend::load_gray(&pair.join("left_img_0.png"))?;
    let right = doorslam_frontend::load_gray(&pair.join("right_img_0.png"))?;
    let orb = doorslam_frontend::detect_orb(&left, 1000)?;
    step(
        "opencv",
        format!(
            "{} ORB features on {}x{} EuRoC V1_01 left image",
            orb.points.len(),
            left.cols(),
            left.rows()
        ),
        t,
    );

    // iceoryx2: the stereo pair written once into a loaned shared-memory sample and read back.
    let t = Instant::now();
    let robot = format!("demo{}", std::process::id());
    let (node, cleaned) = doorslam_ipc::create_node("doorslam-demo")?;
    let service = doorslam_ipc::open_frames(&node, &robot)?;
    let subscriber = service
        .subscriber_builder()
        .create()
        .context("iceoryx2 subscriber")?;
    let publisher = service
        .publisher_builder()
        .create()
        .context("iceoryx2 publisher")?;
    let header = doorslam_ipc::FrameHeader {
        width: left.cols() as u32,
        height: left.rows() as u32,
        ..Default::default()
    };
    let (l, r) = (left.data_bytes()?, right.data_bytes()?);
    let mut sample = publisher.loan_uninit().context("iceoryx2 loan")?;
    doorslam_ipc::StereoFrame::write(sample.payload_mut(), header, l, r)?;
    // SAFETY: `StereoFrame::write` initialized the sample.
    unsafe { sample.assume_init() }
        .send()
        .context("iceoryx2 send")?;
    let Some(received) = subscriber.receive().context("iceoryx2 receive")? else {
        bail!(
            "iceoryx2: the frame published on {} was not received",
            doorslam_ipc::service_name(&robot, doorslam_ipc::Topic::Frames)
        );
    };
    ensure!(
        received.payload().left_image()? == l && received.payload().right_image()? == r,
        "iceoryx2: frame corrupted"
    );
    step(
        "iceoryx2",
        format!(
            "{} KB stereo frame through shared memory ({cleaned} dead nodes cleaned)",
            (l.len() + r.len()) / 1024
        ),
        t,
    );

    // onnxruntime: a generated projection head (not a trained NetVLAD) on the mean ORB bits.
    let t = Instant::now();
    let mut pooled = vec![0f32; 256];
    for d in &orb.descriptors {
        for (bit, p) in pooled.iter_mut().enumerate() {
            *p += ((d[bit / 8] >> (bit % 8)) & 1) as f32 / orb.descriptors.len().max(1) as f32;
        }
    }
    let w: Vec<f32> = (0..256 * 64)
        .map(|i| ((i * 7919 % 251) as f32 / 125.0) - 1.0)
        .collect();
    let head = doorslam_place_recognition::onnx::projection_head(256, 64, &w, &[0.0; 64])
        .context("building ONNX head")?;
    let mut model =
        doorslam_place_recognition::DescriptorModel::from_bytes(&head, "demo-projection-head")?;
    let descriptor = model.describe(&pooled)?;
    let norm = descriptor.iter().map(|v| v * v).sum::<f32>().sqrt();
    step(
        "onnxruntime",
        format!("64-D descriptor from a generated projection head, |d| = {norm:.4}"),
        t,
    );

    // Zenoh: the descriptor from robot a to robot b, two peers on loopback.
    let t = Instant::now();
    let port = std::net::TcpListener::bind("127.0.0.1:0")?
        .local_addr()?
        .port();
    let endpoint = format!("tcp/127.0.0.1:{port}");
    let link = |listen: Vec<String>, connect: Vec<String>| doorslam_team::LinkConfig {
        listen,
        connect,
        multicast_scouting: false,
    };
    let a = doorslam_team::open_peer(&link(vec![endpoint.clone()], vec![]))?;
    let b = doorslam_team::open_peer(&link(vec![], vec![endpoint]))?;
    let key = doorslam_team::key_expr(
        "demo",
        &format!("b{}", std::process::id()),
        "descriptor",
        "a",
    )?;
    let sub = b
        .declare_subscriber(&key)
        .wait()
        .map_err(|e| anyhow::anyhow!("zenoh subscriber: {e}"))?;
    let bytes: Vec<u8> = descriptor.iter().flat_map(|v| v.to_le_bytes()).collect();
    let deadline = Instant::now() + Duration::from_secs(10);
    let got = loop {
        a.put(&key, bytes.clone())
            .wait()
            .map_err(|e| anyhow::anyhow!("zenoh put: {e}"))?;
        if let Some(s) = sub
            .recv_timeout(Duration::from_millis(100))
            .map_err(|e| anyhow::anyhow!("zenoh: {e}"))?
        {
            break s;
        }
        ensure!(
            Instant::now() < deadline,
            "zenoh: no message between loopback peers within 10 s"
        );
    };
    ensure!(
        got.payload().to_bytes().as_ref() == bytes.as_slice(),
        "zenoh: payload corrupted"
    );
    let _ = (a.close().wait(), b.close().wait());
    step(
        "zenoh",
        format!("{} B descriptor between two peers on loopback", bytes.len()),
        t,
    );

    // faer: a tridiagonal SPD system (a 1-D chain of poses), solved by sparse Cholesky.
    let t = Instant::now();
    let n = 1000;
    let mut triplets = Vec::new();
    for i in 0..n {
        triplets.push((i, i, if i == 0 { 3.0 } else { 2.0 }));
        if i > 0 {
            triplets.push((i, i - 1, -1.0));
        }
    }
    let a_mat = doorslam_backend::SparseCholesky::lower_from_triplets(n, &triplets)?;
    let x = doorslam_backend::SparseCholesky::new().solve(&a_mat, &vec![1.0; n])?;
    step(
        "faer",
        format!("{n}x{n} sparse SPD chain solved, x[0] = {:.3}", x[0]),
        t,
    );

    // v4l2: what cameras this machine has (none in CI; the services then use replay).
    let t = Instant::now();
    let cams = doorslam_camera::enumerate_devices();
    step("v4l", format!("{} v4l2 device(s) present", cams.len()), t);
    println!("doorslam demo: all stack checks passed");
    Ok(())
}
