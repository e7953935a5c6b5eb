//! Measurement primitives both processes share: clocks, CPU time, the test images, an
//! in-place checksum, percentiles, and the lookup that tells whether a payload lies in
//! shared memory.

use std::io;

use serde::{Deserialize, Serialize};

fn clock_ns(clock: libc::clockid_t) -> u64 {
    let mut ts = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: `ts` is a valid, writable timespec; both clocks we pass exist on Linux, so
    // the call cannot fail (and a failure would leave zeros, not undefined memory).
    unsafe { libc::clock_gettime(clock, &mut ts) };
    ts.tv_sec as u64 * 1_000_000_000 + ts.tv_nsec as u64
}

/// Restricts the calling process (its threads created from now on, and this one) to one
/// CPU, so publisher and subscriber cannot be placed on the same core by the scheduler.
pub fn pin_to_cpu(cpu: usize) -> io::Result<()> {
    if cpu >= libc::CPU_SETSIZE as usize {
        return Err(io::Error::new(
            io::ErrorKind::InvalidInput,
            format!("CPU {cpu} out of range"),
        ));
    }
    // SAFETY: a zeroed cpu_set_t is the empty set; CPU_SET stays in bounds (checked above);
    // sched_setaffinity reads the set for the call only.
    let rc = unsafe {
        let mut set: libc::cpu_set_t = std::mem::zeroed();
        libc::CPU_SET(cpu, &mut set);
        libc::sched_setaffinity(0, std::mem::size_of::<libc::cpu_set_t>(), &set)
    };
    if rc != 0 {
        return Err(io::Error::last_os_error());
    }
    Ok(())
}

/// Median of the values present (the lower middle one for an even count).
pub fn median(values: impl IntoIterator<Item = Option<f64>>) -> Option<f64> {
    let mut v: Vec<f64> = values.into_iter().flatten().collect();
    v.sort_by(f64::total_cmp);
    (!v.is_empty()).then(|| v[(v.len() - 1) / 2])
}

/// CLOCK_MONOTONIC in nanoseconds: unlike `std::time::Instant`, its value means the same
/// in every process of the machine, so a stamp written by one process can be subtracted
/// from a reading taken in another.
pub fn mono_ns() -> u64 {
    clock_ns(libc::CLOCK_MONOTONIC)
}

/// CPU time (user + system, all threads) consumed by this process so far, in nanoseconds.
/// Same quantity as getrusage(RUSAGE_SELF), at nanosecond rather than microsecond grain.
pub fn cpu_ns() -> u64 {
    clock_ns(libc::CLOCK_PROCESS_CPUTIME_ID)
}

/// CPU time of the calling thread, in nanoseconds: brackets the publisher's one copy.
pub fn thread_cpu_ns() -> u64 {
    clock_ns(libc::CLOCK_THREAD_CPUTIME_ID)
}

/// The deterministic test image both processes generate, so the subscriber can verify a
/// checksum without the publisher sending it.
pub fn test_image(width: u32, height: u32, side: u8) -> Vec<u8> {
    let w = width as usize;
    (0..w * height as usize)
        .map(|i| ((i % w) + (i / w) * 3 + usize::from(side) * 101) as u8)
        .collect()
}

/// A checksum that reads every byte where it lies. Four independent lanes keep the loop
/// vectorizable, so the read costs about what the memory bandwidth costs.
pub fn checksum(bytes: &[u8]) -> u64 {
    let mut lanes = [0u64; 4];
    let mut chunks = bytes.chunks_exact(32);
    for chunk in &mut chunks {
        for (k, lane) in lanes.iter_mut().enumerate() {
            let mut word = [0u8; 8];
            word.copy_from_slice(&chunk[8 * k..8 * k + 8]);
            *lane = lane.wrapping_add(u64::from_le_bytes(word));
        }
    }
    let tail = chunks.remainder().iter().fold(0u64, |acc, &b| {
        acc.wrapping_mul(31).wrapping_add(u64::from(b))
    });
    lanes[0] ^ lanes[1].rotate_left(16) ^ lanes[2].rotate_left(32) ^ lanes[3].rotate_left(48) ^ tail
}

/// Nearest-rank percentile of an ascending slice (`p` in 0..=1).
pub fn percentile(sorted: &[u64], p: f64) -> Option<u64> {
    if sorted.is_empty() {
        return None;
    }
    let rank = (p * sorted.len() as f64).ceil() as usize;
    Some(sorted[rank.clamp(1, sorted.len()) - 1])
}

/// Latency samples of one phase, summarized where they were taken (the raw samples
/// never cross the process boundary).
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct LatencySummary {
    pub count: u64,
    pub p50_ns: Option<u64>,
    pub p99_ns: Option<u64>,
}

impl LatencySummary {
    pub fn from_samples(mut samples: Vec<u64>) -> Self {
        samples.sort_unstable();
        Self {
            count: samples.len() as u64,
            p50_ns: percentile(&samples, 0.50),
            p99_ns: percentile(&samples, 0.99),
        }
    }
}

/// One line of /proc/self/maps: what backs a range of this process's address space.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Mapping {
    /// File backing the range (`/dev/shm/...` for POSIX shared memory), empty if anonymous.
    pub path: String,
    /// `s` in the permissions: writes are visible to every process mapping the object.
    pub shared: bool,
    /// Device and inode of the backing object: equal in two processes means the same memory.
    pub dev: String,
    pub inode: u64,
}

impl Mapping {
    /// Both ranges are shared mappings of one and the same memory object.
    pub fn same_shared_object(&self, other: &Mapping) -> bool {
        self.shared
            && other.shared
            && self.inode != 0
            && self.dev == other.dev
            && self.inode == other.inode
    }
}

/// A snapshot of /proc/self/maps.
#[derive(Debug, Default)]
pub struct Maps {
    ranges: Vec<(usize, usize, Mapping)>,
}

impl Maps {
    pub fn load() -> io::Result<Self> {
        let text = std::fs::read_to_string("/proc/self/maps")?;
        let ranges = text.lines().filter_map(parse_maps_line).collect();
        Ok(Self { ranges })
    }

    /// The mapping that contains all of `[addr, addr + len)`, if one does.
    pub fn find(&self, addr: usize, len: usize) -> Option<&Mapping> {
        let end = addr.checked_add(len)?;
        self.ranges
            .iter()
            .find(|(lo, hi, _)| *lo <= addr && end <= *hi)
            .map(|(_, _, m)| m)
    }
}

fn parse_maps_line(line: &str) -> Option<(usize, usize, Mapping)> {
    let mut fields = line.split_whitespace();
    let (lo, hi) = fields.next()?.split_once('-')?;
    let perms = fields.next()?;
    let _offset = fields.next()?;
    let dev = fields.next()?.to_string();
    let inode = fields.next()?.parse().ok()?;
    let path = fields.collect::<Vec<_>>().join(" ");
    Some((
        usize::from_str_radix(lo, 16).ok()?,
        usize::from_str_radix(hi, 16).ok()?,
        Mapping {
            path,
            shared: perms.as_bytes().get(3) == Some(&b's'),
            dev,
            inode,
        },
    ))
}

/// Finds the mapping of `bytes` in a cached snapshot, reloading the snapshot once on a
/// miss (a transport may map a new segment mid-run). Reading /proc costs ~100 µs, so the
/// cache is what makes a per-frame check affordable.
pub fn mapping_of(cache: &mut Option<Maps>, bytes: &[u8]) -> Option<Mapping> {
    mapping_of_range(cache, bytes.as_ptr() as usize, bytes.len())
}

/// As [`mapping_of`], for memory not (yet) viewable as a byte slice.
pub fn mapping_of_range(cache: &mut Option<Maps>, addr: usize, len: usize) -> Option<Mapping> {
    if let Some(found) = cache.as_ref().and_then(|m| m.find(addr, len)) {
        return Some(found.clone());
    }
    *cache = Maps::load().ok();
    cache.as_ref()?.find(addr, len).cloned()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn percentiles_use_nearest_rank() {
        let v: Vec<u64> = (1..=100).collect();
        assert_eq!(percentile(&v, 0.5), Some(50));
        assert_eq!(percentile(&v, 0.99), Some(99));
        assert_eq!(percentile(&[7], 0.99), Some(7));
        assert_eq!(percentile(&[], 0.5), None);
    }

    #[test]
    fn maps_lines_parse_shared_and_private() {
        let shm = "7f00-7f10 rw-s 00000000 00:1a 4242    /dev/shm/iox2_abc";
        let (lo, hi, m) = parse_maps_line(shm).unwrap();
        assert_eq!((lo, hi), (0x7f00, 0x7f10));
        assert!(m.shared && m.path == "/dev/shm/iox2_abc" && m.inode == 4242);
        let heap = "5500-5600 rw-p 00000000 00:00 0 [heap]";
        assert!(!parse_maps_line(heap).unwrap().2.shared);
    }

    #[test]
    fn a_heap_buffer_is_not_shared_memory() {
        let buf = vec![1u8; 4096];
        let mut cache = None;
        let m = mapping_of(&mut cache, &buf).unwrap();
        assert!(!m.shared);
    }

    #[test]
    fn checksum_sees_every_byte() {
        let img = test_image(752, 480, 0);
        let mut other = img.clone();
        other[752 * 480 - 1] ^= 1;
        assert_ne!(checksum(&img), checksum(&other));
        other[0] ^= 1;
        other[752 * 480 - 1] ^= 1;
        assert_ne!(checksum(&img), checksum(&other));
    }
}
