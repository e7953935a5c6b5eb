//! The place-recognition service of one robot (`doorslam service place-recognition`):
//! keyframes in, place descriptors out, over iceoryx2.
//!
//! - subscribes to `Frames` (lossy, 2 deep) and drains them into a small cache of left
//!   images by frame sequence ([`state::FrameCache`]): a `Keyframe` sample does not carry
//!   its image, NetVLAD needs it;
//! - subscribes to `Keyframes` (reliable): each becomes a job with its image (by
//!   `frame_seq`) and/or its ORB features ([`state::PlaceState::on_keyframe`]); a keyframe
//!   whose frame is no longer cached is counted and logged, and gets no descriptor;
//! - inference runs on a dedicated thread ([`worker::Worker`]), batched when keyframes
//!   queue up, preprocessing in Rust;
//! - publishes one `PlaceDescriptor` per keyframe on `Descriptors`, the 128-D wire form
//!   (L2-normalized float; the team link quantizes it to int8), written in place into the
//!   loaned sample.
//!
//! The model or vocabulary is loaded before the channels open: a missing, corrupt or
//! wrong-shape file stops the service with an error naming the file and what was expected.

pub mod config;
pub mod state;
pub mod worker;

use std::mem::MaybeUninit;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use doorslam_ipc::{
    create_node, Keyframe, Lifecycle, PlaceDescriptor, Receiver, Sender, StereoFrame, Topic,
    MAX_DESCRIPTOR_DIM,
};

pub use config::{BowFeatures, PlaceConfig, PlaceConfigError, PlaceSection};
pub use state::{FrameCache, Job, PlaceReport, PlaceState, Skip};
pub use worker::{describe_jobs, Described, Worker};

use crate::describer::Describer;
use crate::model::PlaceRecognitionError;

/// Failures of the place-recognition service.
#[derive(Debug, thiserror::Error)]
pub enum ServiceError {
    #[error(transparent)]
    Ipc(#[from] doorslam_ipc::IpcError),
    #[error(transparent)]
    Model(#[from] PlaceRecognitionError),
    #[error("starting the inference thread: {0}")]
    Thread(std::io::Error),
    #[error("the inference thread stopped unexpectedly")]
    WorkerGone,
}

/// How long the loop sleeps waiting for a frame before it looks at keyframes and results:
/// a keyframe or a descriptor waits at most this long.
const TICK: Duration = Duration::from_millis(10);

/// Writes one descriptor in place into a (shared-memory) sample: header fields, the
/// values, zeros after them. No `PlaceDescriptor` (16 kB) is built on the stack.
pub fn write_descriptor(
    slot: &mut MaybeUninit<PlaceDescriptor>,
    robot: u32,
    keyframe: u64,
    values: &[f32],
) -> Result<(), String> {
    let n = values.len();
    if n > MAX_DESCRIPTOR_DIM {
        return Err(format!("{n} values exceed {MAX_DESCRIPTOR_DIM}"));
    }
    let p = slot.as_mut_ptr();
    // SAFETY: `p` points to a (maybe uninitialized) PlaceDescriptor; every field is
    // written once through raw pointers (no reference to uninitialized memory is formed):
    // the three header fields, then all MAX_DESCRIPTOR_DIM floats (n copied, the rest
    // zero bits, which is 0.0). The struct is repr(C) without padding (4 + 4 + 8 + 4·4096
    // bytes), so every byte is initialized afterwards.
    unsafe {
        std::ptr::addr_of_mut!((*p).robot).write(robot);
        std::ptr::addr_of_mut!((*p).dim).write(n as u32);
        std::ptr::addr_of_mut!((*p).keyframe).write(keyframe);
        let dst = std::ptr::addr_of_mut!((*p).values).cast::<f32>();
        std::ptr::copy_nonoverlapping(values.as_ptr(), dst, n);
        std::ptr::write_bytes(dst.add(n), 0, MAX_DESCRIPTOR_DIM - n);
    }
    Ok(())
}

/// Loads the describer `config` names (errors name the file and what was expected).
pub fn open_describer(config: &PlaceConfig) -> Result<Describer, PlaceRecognitionError> {
    Describer::open(
        config.method,
        &config.model,
        &config.vocabulary,
        config.threads,
    )
}

/// Publishes described keyframes; the first failed batch stops the service.
fn publish(
    batches: Vec<Result<Vec<Described>, PlaceRecognitionError>>,
    sender: &Sender<PlaceDescriptor>,
    state: &mut PlaceState,
    robot: u32,
) -> Result<(), ServiceError> {
    for batch in batches {
        let batch = batch?;
        state.on_described(batch.len());
        for d in &batch {
            sender.send_with(|slot| write_descriptor(slot, robot, d.keyframe, &d.values))?;
            tracing::debug!(
                keyframe = d.keyframe,
                batch = batch.len(),
                "place: described"
            );
        }
    }
    Ok(())
}

/// Drains the frame queue into the cache.
fn drain_frames(
    frames: &Receiver<StereoFrame>,
    state: &mut PlaceState,
) -> Result<(), ServiceError> {
    while let Some(sample) = frames.try_recv()? {
        take_frame(sample.payload(), state);
    }
    Ok(())
}

fn take_frame(frame: &StereoFrame, state: &mut PlaceState) {
    match frame.left_image() {
        Ok(left) => state.on_frame(frame.header(), left),
        Err(e) => tracing::warn!(seq = frame.header().seq, "place: frame skipped: {e}"),
    }
}

/// Queued keyframes become jobs, handed over together; skipped ones are logged.
fn drain_keyframes(
    keyframes: &Receiver<Keyframe>,
    state: &mut PlaceState,
    worker: &mut Worker,
) -> Result<(), ServiceError> {
    let mut jobs = Vec::new();
    while let Some(sample) = keyframes.try_recv()? {
        match state.on_keyframe(sample.payload()) {
            Ok(job) => jobs.push(job),
            Err(skip @ Skip::Duplicate { .. }) => tracing::debug!("place: {skip}"),
            Err(skip) => tracing::warn!("place: no descriptor: {skip}"),
        }
    }
    if worker.submit(jobs) {
        Ok(())
    } else {
        Err(ServiceError::WorkerGone)
    }
}

/// Runs until SIGTERM/SIGINT or until `stop` is set (tests run it on a thread).
pub fn run(config: &PlaceConfig, stop: &AtomicBool) -> Result<PlaceReport, ServiceError> {
    let describer = open_describer(config)?;
    tracing::info!(
        method = config.method.name(),
        model = %config.model.display(),
        vocabulary = %config.vocabulary.display(),
        threshold = config.match_threshold,
        batch_size = config.batch_size,
        "place: descriptor loaded"
    );
    let (node, cleaned) = create_node("doorslam-place-recognition")?;
    if cleaned > 0 {
        tracing::warn!(cleaned, "place: removed shared memory of dead processes");
    }
    let frames = Receiver::<StereoFrame>::new(&node, &config.robot, Topic::Frames)?;
    let keyframes = Receiver::<Keyframe>::new(&node, &config.robot, Topic::Keyframes)?;
    let descriptors = Sender::<PlaceDescriptor>::new(&node, &config.robot, Topic::Descriptors)?;
    let mut state = PlaceState::new(
        config.robot_index,
        config.method,
        config.bow_features,
        config.frame_cache,
    );
    let mut worker = Worker::spawn(describer, config.batch_size).map_err(ServiceError::Thread)?;
    let mut lifecycle = Lifecycle::new();
    lifecycle.ready(&format!("{} descriptors", config.method.name()));
    tracing::info!(robot = %config.robot, "place: ready (frames, keyframes -> descriptors)");

    while lifecycle.keep_going(&node) && !stop.load(Ordering::Relaxed) {
        // Frames come at camera rate and a keyframe follows its frame: sleep on frames,
        // then take every queued frame before any keyframe, so a keyframe finds its image.
        if let Some(sample) = frames.recv_timeout(TICK)? {
            take_frame(sample.payload(), &mut state);
        }
        drain_frames(&frames, &mut state)?;
        drain_keyframes(&keyframes, &mut state, &mut worker)?;
        let ready = worker.ready();
        if ready.is_empty() {
            // Idle: a consumer restarted since the last descriptor gets what it missed.
            descriptors.catch_up_receivers()?;
        }
        publish(ready, &descriptors, &mut state, config.robot_index)?;
    }
    lifecycle.stopping();
    // Producers stop first (`doorslam up` and the units stop in reverse start order):
    // what reached the queue is described before the service exits.
    drain_frames(&frames, &mut state)?;
    drain_keyframes(&keyframes, &mut state, &mut worker)?;
    publish(
        worker.finish(),
        &descriptors,
        &mut state,
        config.robot_index,
    )?;
    descriptors.catch_up_receivers()?;
    let report = state.report().clone();
    tracing::info!(
        frames = report.frames,
        dropped_frames = report.dropped_frames,
        keyframes = report.keyframes,
        described = report.described,
        frame_not_cached = report.frame_not_cached,
        duplicates = report.duplicates,
        wrong_robot = report.wrong_robot,
        batches = report.batches,
        largest_batch = report.largest_batch,
        undelivered = descriptors.undelivered(),
        "place: stopped"
    );
    Ok(report)
}
