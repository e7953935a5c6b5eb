//! The back-end journal never destroys data: torn tails are cut, corruption in the middle
//! is moved aside byte for byte, and files that are not this robot's journal in a readable
//! version are refused and left untouched. Every test checks exact file contents.

use std::path::{Path, PathBuf};

use doorslam_backend::journal::{
    BadRecord, Entry, Journal, JournalError, Recovery, FORMAT_VERSION, MAGIC, MAX_RECORD_LEN,
};
use proptest::prelude::*;

const ROBOT: &str = "r1";

fn keyframe(id: u64) -> Entry {
    Entry::Keyframe {
        id,
        stamp_ns: 1_000 * id,
        pose: [id as f64, 0.5, -1.0, 0.0, 0.0, 0.0, 1.0],
    }
}

fn odometry(from: u64) -> Entry {
    Entry::Odometry {
        from,
        to: from + 1,
        relative: [1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0],
        information: std::array::from_fn(|k| k as f64),
    }
}

/// Keyframes and edges alternating, so both record sizes occur.
fn entries(n: usize) -> Vec<Entry> {
    (0..n as u64)
        .map(|k| {
            if k % 2 == 0 {
                keyframe(k / 2)
            } else {
                odometry(k / 2)
            }
        })
        .collect()
}

/// The header `open` writes for `robot`, spelled out independently of the library.
fn header(robot: &str) -> Vec<u8> {
    let mut h = b"DSJOURNL".to_vec();
    h.extend_from_slice(&1u32.to_le_bytes());
    h.push(robot.len() as u8);
    h.extend_from_slice(robot.as_bytes());
    let crc = crc32fast::hash(&h);
    h.extend_from_slice(&crc.to_le_bytes());
    h
}

/// A journal of `ROBOT` holding `es`; returns its bytes and the end offset of each record.
fn write_journal(path: &Path, es: &[Entry]) -> (Vec<u8>, Vec<usize>) {
    let (mut j, r) = Journal::open(path, ROBOT).unwrap();
    assert!(r.fresh && r.entries.is_empty());
    let mut ends = Vec::new();
    for e in es {
        j.append(e).unwrap();
        ends.push(std::fs::metadata(path).unwrap().len() as usize);
    }
    (std::fs::read(path).unwrap(), ends)
}

/// A record in the journal's framing with any payload.
fn raw_record(payload: &[u8]) -> Vec<u8> {
    let mut r = (payload.len() as u32).to_le_bytes().to_vec();
    r.extend_from_slice(&crc32fast::hash(payload).to_le_bytes());
    r.extend_from_slice(payload);
    r
}

fn files_in(dir: &Path) -> Vec<PathBuf> {
    let mut v: Vec<PathBuf> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .collect();
    v.sort();
    v
}

/// Opens, checks that appending continues after what was recovered, and returns the
/// recovery.
fn open_and_append(path: &Path) -> Recovery {
    let (mut j, r) = Journal::open(path, ROBOT).unwrap();
    let extra = keyframe(1000);
    j.append(&extra).unwrap();
    drop(j);
    let again = Journal::read(path).unwrap();
    let mut expected = r.entries.clone();
    expected.push(extra);
    assert_eq!(again.entries, expected, "appending after recovery");
    assert_eq!(again.truncated_bytes, 0);
    assert_eq!(again.corruption, None);
    r
}

#[test]
fn a_new_journal_has_the_header_and_round_trips() {
    let tmp = tempfile::tempdir().unwrap();
    let path = tmp.path().join("sub").join("backend.journal");
    let es = entries(5);
    let (bytes, ends) = write_journal(&path, &es);
    assert_eq!(&bytes[..header(ROBOT).len()], header(ROBOT).as_slice());
    assert_eq!(MAGIC, *b"DSJOURNL");
    assert_eq!(FORMAT_VERSION, 1);
    // 8-byte framing + 73-byte keyframes and 241-byte edges.
    let h = header(ROBOT).len();
    assert_eq!(ends, vec![h + 81, h + 330, h + 411, h + 660, h + 741]);

    let (_, r) = Journal::open(&path, ROBOT).unwrap();
    assert_eq!(
        r,
        Recovery {
            robot: Some(ROBOT.into()),
            entries: es.clone(),
            ..Default::default()
        }
    );
    assert_eq!(Journal::read(&path).unwrap(), r);
    assert_eq!(std::fs::read(&path).unwrap(), bytes);
}

#[test]
fn an_empty_file_becomes_a_fresh_journal() {
    let tmp = tempfile::tempdir().unwrap();
    let path = tmp.path().join("backend.journal");
    std::fs::write(&path, b"").unwrap();
    assert!(Journal::read(&path).unwrap().fresh);
    let r = open_and_append(&path);
    assert!(r.fresh);
    assert_eq!(r.torn_header_bytes, 0);
    assert!(r.entries.is_empty());
    // Exactly what a journal created from nothing holds after the same append.
    let (reference, _) = write_journal(&tmp.path().join("ref"), &[keyframe(1000)]);
    assert_eq!(std::fs::read(&path).unwrap(), reference);
}

#[test]
fn a_header_torn_at_creation_is_rewritten_and_reported() {
    let full = header(ROBOT);
    for cut in 1..full.len() {
        let tmp = tempfile::tempdir().unwrap();
        let path = tmp.path().join("backend.journal");
        std::fs::write(&path, &full[..cut]).unwrap();
        let r = open_and_append(&path);
        assert!(r.fresh, "cut {cut}");
        assert_eq!(r.torn_header_bytes, cut as u64, "cut {cut}");
        assert_eq!(
            &std::fs::read(&path).unwrap()[..full.len()],
            full.as_slice()
        );
    }
}

#[test]
fn a_torn_header_of_another_robot_is_refused_and_left_alone() {
    let tmp = tempfile::tempdir().unwrap();
    let path = tmp.path().join("backend.journal");
    let other = header("r2");
    let torn = &other[..other.len() - 2];
    std::fs::write(&path, torn).unwrap();
    let err = Journal::open(&path, ROBOT).err().unwrap();
    assert!(
        matches!(err, JournalError::BadHeader { .. }),
        "{err:?} for a torn header naming r2"
    );
    assert_eq!(std::fs::read(&path).unwrap(), torn);
}

#[test]
fn a_torn_last_record_is_cut_and_earlier_records_kept() {
    let es = entries(4);
    let tmp = tempfile::tempdir().unwrap();
    let (bytes, ends) = write_journal(&tmp.path().join("ref"), &es);
    // Cut inside the last record's payload, inside its [len][crc], and right after it.
    for cut in [ends[3] - 10, ends[2] + 3, ends[2] + 8, ends[2] + 9] {
        let path = tmp.path().join(format!("cut{cut}"));
        std::fs::write(&path, &bytes[..cut]).unwrap();
        let read = Journal::read(&path).unwrap();
        assert_eq!(read.entries, es[..3]);
        assert_eq!(read.truncated_bytes, (cut - ends[2]) as u64);
        assert_eq!(
            std::fs::read(&path).unwrap(),
            &bytes[..cut],
            "read changes nothing"
        );

        let r = open_and_append(&path);
        assert_eq!(r.entries, es[..3], "cut at {cut}");
        assert_eq!(r.truncated_bytes, (cut - ends[2]) as u64);
        assert_eq!(r.corruption, None);
        assert_eq!(&std::fs::read(&path).unwrap()[..ends[2]], &bytes[..ends[2]]);
    }
    // Nothing but the journals: no side file for a torn tail.
    assert_eq!(files_in(tmp.path()).len(), 5);
}

#[test]
fn a_checksum_failure_of_the_final_record_at_the_end_of_file_is_a_torn_tail() {
    let es = entries(3);
    let tmp = tempfile::tempdir().unwrap();
    let path = tmp.path().join("backend.journal");
    let (mut bytes, ends) = write_journal(&path, &es);
    *bytes.last_mut().unwrap() ^= 0x01;
    std::fs::write(&path, &bytes).unwrap();
    let r = open_and_append(&path);
    assert_eq!(r.entries, es[..2]);
    assert_eq!(r.truncated_bytes, (ends[2] - ends[1]) as u64);
    assert_eq!(r.corruption, None);
}

#[test]
fn a_zero_filled_tail_is_cut() {
    let es = entries(2);
    let tmp = tempfile::tempdir().unwrap();
    let path = tmp.path().join("backend.journal");
    let (mut bytes, _) = write_journal(&path, &es);
    bytes.extend_from_slice(&[0; 4096]);
    std::fs::write(&path, &bytes).unwrap();
    let r = open_and_append(&path);
    assert_eq!(r.entries, es);
    assert_eq!(r.truncated_bytes, 4096);
    assert_eq!(r.corruption, None);
}

/// Opens a journal with a bad record at `offset` and checks the corruption handling:
/// records before it kept, everything from it on in a new side file, journal appendable.
fn assert_preserved(dir: &Path, path: &Path, bytes: &[u8], offset: usize, kept: &[Entry]) {
    let before = files_in(dir);
    let read = Journal::read(path).unwrap();
    let c = read
        .corruption
        .clone()
        .expect("read reports the corruption");
    assert_eq!(
        (c.offset, c.bytes, c.preserved),
        (offset as u64, (bytes.len() - offset) as u64, None)
    );
    assert_eq!(std::fs::read(path).unwrap(), bytes, "read changes nothing");

    let r = open_and_append(path);
    assert_eq!(r.entries, kept);
    assert_eq!(r.truncated_bytes, 0);
    let c = r.corruption.expect("corruption reported");
    assert_eq!(c.offset, offset as u64);
    assert_eq!(c.bytes, (bytes.len() - offset) as u64);
    let side = c.preserved.expect("side file");
    assert_eq!(side.parent(), path.parent());
    let name = side.file_name().unwrap().to_str().unwrap();
    let prefix = format!("{}.corrupt-", path.file_name().unwrap().to_str().unwrap());
    assert!(name.starts_with(&prefix), "{name}");
    assert!(!before.contains(&side), "a new side file");
    assert_eq!(
        std::fs::read(&side).unwrap(),
        &bytes[offset..],
        "tail byte for byte"
    );
    assert_eq!(&std::fs::read(path).unwrap()[..offset], &bytes[..offset]);
}

#[test]
fn a_flipped_byte_in_the_middle_is_preserved_in_a_side_file() {
    let es = entries(6);
    let tmp = tempfile::tempdir().unwrap();
    let path = tmp.path().join("backend.journal");
    let (mut bytes, ends) = write_journal(&path, &es);
    // A payload byte of record 2 (an edge's relative pose).
    bytes[ends[1] + 30] ^= 0x40;
    std::fs::write(&path, &bytes).unwrap();
    assert!(matches!(
        Journal::read(&path).unwrap().corruption.unwrap().reason,
        BadRecord::Checksum { .. }
    ));
    assert_preserved(tmp.path(), &path, &bytes, ends[1], &es[..2]);
}

#[test]
fn a_second_corruption_gets_its_own_side_file() {
    let es = entries(4);
    let tmp = tempfile::tempdir().unwrap();
    let path = tmp.path().join("backend.journal");
    let (mut bytes, ends) = write_journal(&path, &es);
    bytes[ends[1] + 30] ^= 0x40;
    std::fs::write(&path, &bytes).unwrap();
    assert_preserved(tmp.path(), &path, &bytes, ends[1], &es[..2]);
    let first = files_in(tmp.path());
    let first_side = first.iter().find(|p| *p != &path).unwrap().clone();
    let first_contents = std::fs::read(&first_side).unwrap();

    // Now the journal is records 0, 1 and keyframe 1000. Append one more and damage
    // keyframe 1000, most likely within the same second: the name gets a counter.
    let (mut j, _) = Journal::open(&path, ROBOT).unwrap();
    j.append(&keyframe(7)).unwrap();
    drop(j);
    let mut again = std::fs::read(&path).unwrap();
    let kf1000 = again.len() - 2 * 81;
    assert_eq!(kf1000, ends[1]);
    again[kf1000 + 40] ^= 0x01;
    std::fs::write(&path, &again).unwrap();
    assert_preserved(tmp.path(), &path, &again, kf1000, &es[..2]);
    assert_eq!(files_in(tmp.path()).len(), 3);
    assert_eq!(std::fs::read(&first_side).unwrap(), first_contents);
}

#[test]
fn an_unknown_kind_from_a_newer_version_is_preserved_not_skipped() {
    let es = entries(4);
    let tmp = tempfile::tempdir().unwrap();
    let (reference, ends) = write_journal(&tmp.path().join("ref"), &es);
    let unknown = raw_record(&[200, 1, 2, 3, 4, 5, 6, 7, 8, 9]);
    // In the middle, and as the very last record (complete, so not a tear).
    for (name, at) in [("middle", ends[1]), ("last", ends[3])] {
        let path = tmp.path().join(name);
        let mut bytes = reference[..at].to_vec();
        bytes.extend_from_slice(&unknown);
        bytes.extend_from_slice(&reference[at..]);
        std::fs::write(&path, &bytes).unwrap();
        assert_eq!(
            Journal::read(&path).unwrap().corruption.unwrap().reason,
            BadRecord::UnknownKind { kind: 200 }
        );
        let n = ends.iter().filter(|e| **e <= at).count();
        assert_preserved(tmp.path(), &path, &bytes, at, &es[..n]);
    }
}

#[test]
fn an_implausible_length_in_the_middle_is_preserved_and_never_allocated() {
    let es = entries(4);
    let tmp = tempfile::tempdir().unwrap();
    let path = tmp.path().join("backend.journal");
    let (reference, ends) = write_journal(&path, &es);
    let mut bytes = reference.clone();
    bytes[ends[0]..ends[0] + 4].copy_from_slice(&u32::MAX.to_le_bytes());
    std::fs::write(&path, &bytes).unwrap();
    assert_eq!(
        Journal::read(&path).unwrap().corruption.unwrap().reason,
        BadRecord::Length { len: u32::MAX }
    );
    assert_preserved(tmp.path(), &path, &bytes, ends[0], &es[..1]);

    // Just above the bound, at the very end of the file: still not a tear.
    let path = tmp.path().join("big");
    let mut bytes = reference[..ends[3]].to_vec();
    bytes.extend_from_slice(&(MAX_RECORD_LEN + 1).to_le_bytes());
    bytes.extend_from_slice(&[1, 2, 3, 4, 1]);
    std::fs::write(&path, &bytes).unwrap();
    assert_preserved(tmp.path(), &path, &bytes, ends[3], &es);
}

#[test]
fn a_damaged_length_running_past_the_end_is_not_taken_for_a_tear() {
    let es = entries(5);
    let tmp = tempfile::tempdir().unwrap();
    let path = tmp.path().join("backend.journal");
    let (mut bytes, ends) = write_journal(&path, &es);
    // Keyframe record 2 claims 60000 bytes: past the end of the file, but records follow.
    bytes[ends[1]..ends[1] + 4].copy_from_slice(&60_000u32.to_le_bytes());
    std::fs::write(&path, &bytes).unwrap();
    assert_eq!(
        Journal::read(&path).unwrap().corruption.unwrap().reason,
        BadRecord::Size {
            kind: 1,
            len: 60_000,
            expected: 73
        }
    );
    assert_preserved(tmp.path(), &path, &bytes, ends[1], &es[..2]);
}

/// Checks that `open` and `read` refuse the file with an error matching `check` whose
/// message names the file, and leave it byte for byte as it was, with no side file.
fn assert_refused(path: &Path, robot: &str, check: impl Fn(&JournalError) -> bool) -> String {
    let dir = path.parent().unwrap();
    let before = std::fs::read(path).unwrap();
    let files = files_in(dir);
    let err = Journal::open(path, robot).err().expect("open refuses");
    assert!(check(&err), "{err:?}");
    let msg = err.to_string();
    assert!(msg.contains(&path.display().to_string()), "{msg}");
    assert_eq!(std::fs::read(path).unwrap(), before, "file untouched");
    assert_eq!(files_in(dir), files, "no file added");
    msg
}

#[test]
fn the_journal_of_another_robot_is_refused() {
    let tmp = tempfile::tempdir().unwrap();
    let path = tmp.path().join("backend.journal");
    write_journal(&path, &entries(3));
    let msg = assert_refused(&path, "r2", |e| {
        matches!(e, JournalError::OtherRobot { found, expected, .. }
            if found == ROBOT && expected == "r2")
    });
    assert!(msg.contains("\"r1\"") && msg.contains("\"r2\""), "{msg}");
    // read takes any robot and says whose it is.
    assert_eq!(Journal::read(&path).unwrap().robot.as_deref(), Some(ROBOT));
}

#[test]
fn a_newer_format_version_is_refused() {
    let tmp = tempfile::tempdir().unwrap();
    let path = tmp.path().join("backend.journal");
    let (mut bytes, _) = write_journal(&path, &entries(3));
    let h = header(ROBOT).len();
    bytes[8..12].copy_from_slice(&2u32.to_le_bytes());
    let crc = crc32fast::hash(&bytes[..h - 4]);
    bytes[h - 4..h].copy_from_slice(&crc.to_le_bytes());
    // A newer version may also use record kinds this one does not know.
    bytes.extend(raw_record(&[9; 20]));
    std::fs::write(&path, &bytes).unwrap();
    let msg = assert_refused(&path, ROBOT, |e| {
        matches!(
            e,
            JournalError::NewerVersion {
                found: 2,
                supported: 1,
                ..
            }
        )
    });
    assert!(
        msg.contains("version 2") && msg.contains("version 1"),
        "{msg}"
    );
    assert!(matches!(
        Journal::read(&path),
        Err(JournalError::NewerVersion { found: 2, .. })
    ));
}

#[test]
fn a_file_that_is_not_a_journal_is_refused() {
    let tmp = tempfile::tempdir().unwrap();
    for (name, contents) in [
        ("text", b"robot = \"r1\"\n# not a journal\n".to_vec()),
        ("one-byte", b"x".to_vec()),
        ("magic-prefix-then-junk", b"DSJOURxyz0000000000".to_vec()),
    ] {
        let path = tmp.path().join(name);
        std::fs::write(&path, &contents).unwrap();
        assert_refused(&path, ROBOT, |e| {
            matches!(e, JournalError::NotAJournal { .. })
        });
        assert!(matches!(
            Journal::read(&path),
            Err(JournalError::NotAJournal { .. })
        ));
    }
}

#[test]
fn a_headerless_journal_of_the_old_format_is_refused() {
    let tmp = tempfile::tempdir().unwrap();
    let (reference, _) = write_journal(&tmp.path().join("ref"), &entries(3));
    let path = tmp.path().join("backend.journal");
    std::fs::write(&path, &reference[header(ROBOT).len()..]).unwrap();
    let msg = assert_refused(&path, ROBOT, |e| {
        matches!(e, JournalError::Unversioned { .. })
    });
    assert!(msg.contains("no header"), "{msg}");
}

#[test]
fn a_damaged_header_is_refused() {
    let tmp = tempfile::tempdir().unwrap();
    let path = tmp.path().join("backend.journal");
    let (mut bytes, _) = write_journal(&path, &entries(2));
    // The robot id "r1" damaged to "r3": the header checksum catches it.
    bytes[14] ^= 0x02;
    std::fs::write(&path, &bytes).unwrap();
    assert_refused(
        &path,
        ROBOT,
        |e| matches!(e, JournalError::BadHeader { reason, .. } if reason.contains("checksum")),
    );
}

#[test]
fn a_robot_id_that_does_not_fit_is_an_error() {
    let tmp = tempfile::tempdir().unwrap();
    let path = tmp.path().join("backend.journal");
    for robot in [String::new(), "x".repeat(65)] {
        assert!(matches!(
            Journal::open(&path, &robot),
            Err(JournalError::RobotId { .. })
        ));
    }
    assert!(!path.exists());
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]

    /// Cut anywhere after the header: every complete record before the cut survives and
    /// only the partial one is dropped.
    #[test]
    fn any_cut_keeps_every_complete_record(n in 1usize..8, cut_frac in 0.0f64..1.0) {
        let es = entries(n);
        let tmp = tempfile::tempdir().unwrap();
        let path = tmp.path().join("backend.journal");
        let (bytes, ends) = write_journal(&path, &es);
        let h = header(ROBOT).len();
        let cut = h + ((bytes.len() - h) as f64 * cut_frac) as usize;
        std::fs::write(&path, &bytes[..cut]).unwrap();
        let complete = ends.iter().filter(|e| **e <= cut).count();
        let good = if complete == 0 { h } else { ends[complete - 1] };
        let r = open_and_append(&path);
        prop_assert_eq!(&r.entries[..], &es[..complete]);
        prop_assert_eq!(r.truncated_bytes, (cut - good) as u64);
        prop_assert_eq!(r.corruption, None);
    }

    /// Damage any byte of any record: the records before it survive, and the journal and
    /// the side file together hold every byte, except for a torn last record.
    #[test]
    fn any_damaged_byte_loses_nothing_but_a_torn_last_record(
        n in 2usize..8, at_frac in 0.0f64..1.0, xor in 1u8..=255,
    ) {
        let es = entries(n);
        let tmp = tempfile::tempdir().unwrap();
        let path = tmp.path().join("backend.journal");
        let (mut bytes, ends) = write_journal(&path, &es);
        let h = header(ROBOT).len();
        let at = h + ((bytes.len() - h) as f64 * at_frac) as usize;
        bytes[at] ^= xor;
        std::fs::write(&path, &bytes).unwrap();
        let damaged = ends.iter().filter(|e| **e <= at).count();
        let good = if damaged == 0 { h } else { ends[damaged - 1] };
        let r = open_and_append(&path);
        prop_assert_eq!(&r.entries[..], &es[..damaged]);
        match r.corruption {
            Some(c) => {
                prop_assert_eq!(c.offset, good as u64);
                let side = std::fs::read(c.preserved.unwrap()).unwrap();
                prop_assert_eq!(&side[..], &bytes[good..]);
            }
            None => {
                prop_assert_eq!(damaged, n - 1, "only the last record may be cut");
                prop_assert_eq!(r.truncated_bytes, (bytes.len() - good) as u64);
            }
        }
    }
}
