//! The inference thread: takes the keyframes queued for it, describes up to `batch_size`
//! of them in one call (one onnxruntime run for NetVLAD), hands the wire-form descriptors
//! back. The iceoryx2 loop never waits for inference, so it keeps draining frames.

use std::sync::mpsc;
use std::thread::JoinHandle;

use super::state::Job;
use crate::describer::{Describer, KeyframeInput};
use crate::model::PlaceRecognitionError;

/// One keyframe's wire-form descriptor (128 values, L2-normalized).
#[derive(Debug, Clone, PartialEq)]
pub struct Described {
    pub keyframe: u64,
    pub values: Vec<f32>,
}

/// Describes a batch of jobs at once.
pub fn describe_jobs(
    describer: &mut Describer,
    jobs: &[Job],
) -> Result<Vec<Described>, PlaceRecognitionError> {
    let inputs: Vec<KeyframeInput<'_>> = jobs
        .iter()
        .map(|j| KeyframeInput {
            image: j.image.as_deref(),
            features: &j.features,
        })
        .collect();
    let values = describer.describe_wire(&inputs)?;
    Ok(jobs
        .iter()
        .zip(values)
        .map(|(j, values)| Described {
            keyframe: j.keyframe,
            values,
        })
        .collect())
}

type BatchResult = Result<Vec<Described>, PlaceRecognitionError>;

/// The inference thread and its two queues. Jobs go over in groups (what one pass of the
/// service loop took from the keyframe queue), so a burst of keyframes is one batch
/// however the threads are scheduled.
pub struct Worker {
    jobs: Option<mpsc::Sender<Vec<Job>>>,
    results: mpsc::Receiver<BatchResult>,
    handle: Option<JoinHandle<()>>,
    /// Jobs submitted and not yet returned.
    pending: usize,
}

impl Worker {
    /// Starts the thread; it owns the describer from now on.
    pub fn spawn(mut describer: Describer, batch_size: usize) -> std::io::Result<Self> {
        let (job_tx, job_rx) = mpsc::channel::<Vec<Job>>();
        let (result_tx, result_rx) = mpsc::channel::<BatchResult>();
        let batch_size = batch_size.max(1);
        let handle = std::thread::Builder::new()
            .name("place-inference".into())
            .spawn(move || {
                let mut queued = std::collections::VecDeque::new();
                loop {
                    // Sleep only when nothing is queued; then take all that arrived.
                    if queued.is_empty() {
                        match job_rx.recv() {
                            Ok(jobs) => queued.extend(jobs),
                            Err(_) => break, // the service dropped its end: done
                        }
                    }
                    queued.extend(job_rx.try_iter().flatten());
                    let n = queued.len().min(batch_size);
                    let batch: Vec<Job> = queued.drain(..n).collect();
                    if result_tx
                        .send(describe_jobs(&mut describer, &batch))
                        .is_err()
                    {
                        break;
                    }
                }
            })?;
        Ok(Self {
            jobs: Some(job_tx),
            results: result_rx,
            handle: Some(handle),
            pending: 0,
        })
    }

    /// Queues jobs (described in batches of up to `batch_size`). `false` if the thread is
    /// gone (it panicked).
    pub fn submit(&mut self, jobs: Vec<Job>) -> bool {
        if jobs.is_empty() {
            return true;
        }
        let n = jobs.len();
        let sent = self.jobs.as_ref().is_some_and(|tx| tx.send(jobs).is_ok());
        self.pending += if sent { n } else { 0 };
        sent
    }

    /// Jobs queued or being described.
    pub fn pending(&self) -> usize {
        self.pending
    }

    /// The batches described so far (without waiting).
    pub fn ready(&mut self) -> Vec<BatchResult> {
        let out: Vec<BatchResult> = self.results.try_iter().collect();
        self.account(&out);
        out
    }

    fn account(&mut self, results: &[BatchResult]) {
        for r in results {
            // A failed batch returns no count: the loop stops on it anyway.
            let n = r.as_ref().map_or(self.pending, Vec::len);
            self.pending = self.pending.saturating_sub(n);
        }
    }

    /// Describes what is still queued, stops the thread and returns the last batches.
    pub fn finish(mut self) -> Vec<BatchResult> {
        self.jobs = None; // the thread's recv fails once the queue is empty
        let mut out = Vec::new();
        if let Some(h) = self.handle.take() {
            let _ = h.join();
        }
        out.extend(self.results.try_iter());
        self.account(&out);
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bow::Vocabulary;
    use crate::projection::Projection;

    /// A 4-word vocabulary with a 4 -> 2 projection, no model file needed.
    fn describer() -> Describer {
        let words: Vec<[u8; 32]> = (0..4u8).map(|i| [i * 60; 32]).collect();
        let samples: Vec<Vec<f32>> = (0..8)
            .map(|i| (0..4).map(|w| ((i * 7 + w * 3) % 5) as f32).collect())
            .collect();
        Describer::BagOfWords(Vocabulary {
            words,
            idf: vec![1.0; 4],
            projection: Some(Projection::fit(&samples, 2, 0.0).unwrap()),
        })
    }

    #[test]
    fn a_group_of_jobs_is_described_in_batches_of_at_most_batch_size() {
        let mut worker = Worker::spawn(describer(), 4).unwrap();
        let jobs: Vec<Job> = (0..10u64)
            .map(|k| Job {
                keyframe: k,
                image: None,
                features: vec![[(k * 25) as u8; 32]; 3],
            })
            .collect();
        assert!(worker.submit(jobs));
        assert_eq!(worker.pending(), 10);
        let batches = worker.finish();
        let sizes: Vec<usize> = batches.iter().map(|b| b.as_ref().unwrap().len()).collect();
        assert_eq!(sizes, [4, 4, 2]);
        let keyframes: Vec<u64> = batches
            .into_iter()
            .flat_map(|b| b.unwrap())
            .map(|d| d.keyframe)
            .collect();
        assert_eq!(keyframes, (0..10).collect::<Vec<_>>());
    }

    #[test]
    fn a_job_without_its_input_fails_its_batch_by_name() {
        let mut worker = Worker::spawn(describer(), 4).unwrap();
        let job = Job {
            keyframe: 3,
            image: None,
            features: vec![],
        };
        assert!(worker.submit(vec![job]));
        let err = worker.finish().remove(0).unwrap_err();
        assert!(
            matches!(err, PlaceRecognitionError::MissingInput { index: 0, .. }),
            "{err}"
        );
    }
}
