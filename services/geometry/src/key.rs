//! Multi-robot keys, GTSAM's convention: `key = (robot_char << 56) | index`.
//!
//! A key names one pose of one robot across the whole team, so it travels in files (g2o),
//! messages and journals. Indices must fit in 56 bits: a larger one would silently alias
//! another robot's pose, so [`symbol`] refuses it.
//!
//! Robots are numbered 0..[`MAX_ROBOTS`] and their key character is the number's place in
//! [`ALPHABET`]: `'a'..='z'` for robots 0–25, then `'A'..='Z'` for 26–51, as
//! distributed_mapper writes teams of more than 26 robots (its `runDistributedMapper.cpp`
//! uses the same 52-character string). `'a' + robot` is wrong past 25: use
//! [`robot_char`] / [`robot_of_char`], the one mapping every reader and writer shares (the
//! wire format's robot byte is the robot number, g2o files carry the character).

/// Indices are the low 56 bits of a key.
pub const INDEX_BITS: u32 = 56;
/// The largest per-robot index a key can hold.
pub const MAX_INDEX: u64 = (1 << INDEX_BITS) - 1;
/// Robot key characters, by robot number.
pub const ALPHABET: &[u8; 52] = b"abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ";
/// Robots are the characters of [`ALPHABET`]: numbers `0..MAX_ROBOTS`.
pub const MAX_ROBOTS: u8 = 52;

/// A key that cannot be built.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum KeyError {
    #[error("pose index {index} does not fit in a multi-robot key (at most 2^56 - 1)")]
    IndexTooLarge { index: u64 },
    #[error(
        "robot {robot} out of range (a key holds robots 0..{MAX_ROBOTS}, 'a'..'z' then 'A'..'Z')"
    )]
    RobotOutOfRange { robot: u32 },
}

/// The key robot of a robot's index in the team (config, samples, messages carry it as
/// `u32`): below [`MAX_ROBOTS`].
pub fn robot_index(index: u32) -> Result<u8, KeyError> {
    u8::try_from(index)
        .ok()
        .filter(|r| *r < MAX_ROBOTS)
        .ok_or(KeyError::RobotOutOfRange { robot: index })
}

/// The key character of robot `robot` (0 = 'a', 25 = 'z', 26 = 'A', 51 = 'Z').
pub fn robot_char(robot: u8) -> Result<char, KeyError> {
    ALPHABET
        .get(usize::from(robot))
        .map(|&c| c as char)
        .ok_or(KeyError::RobotOutOfRange {
            robot: robot.into(),
        })
}

/// The robot number of a key character, `None` for any other byte.
pub fn robot_of_char(c: u8) -> Option<u8> {
    match c {
        b'a'..=b'z' => Some(c - b'a'),
        b'A'..=b'Z' => Some(c - b'A' + 26),
        _ => None,
    }
}

/// The key of pose `index` of robot `robot` (0 = 'a', 1 = 'b', ..., 26 = 'A', ...).
pub fn symbol(robot: u8, index: u64) -> Result<u64, KeyError> {
    let c = robot_char(robot_index(robot.into())?)?;
    if index > MAX_INDEX {
        return Err(KeyError::IndexTooLarge { index });
    }
    Ok((c as u64) << INDEX_BITS | index)
}

/// The robot (0 = 'a') of a multi-robot key, or `None` for a plain single-robot index.
pub fn robot(key: u64) -> Option<u8> {
    robot_of_char((key >> INDEX_BITS) as u8)
}

/// The per-robot index of a key.
pub fn index(key: u64) -> u64 {
    if robot(key).is_some() {
        key & MAX_INDEX
    } else {
        key
    }
}

/// `a12`-style label for messages, or the plain number.
pub fn label(key: u64) -> String {
    match robot(key).and_then(|r| robot_char(r).ok()) {
        Some(c) => format!("{c}{}", index(key)),
        None => key.to_string(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_and_limits() {
        let k = symbol(2, 12).unwrap();
        assert_eq!(
            (robot(k), index(k), label(k)),
            (Some(2), 12, "c12".to_string())
        );
        assert_eq!(index(symbol(0, MAX_INDEX).unwrap()), MAX_INDEX);
        // 2^56 would have been masked to 0 and aliased pose a0.
        assert_eq!(
            symbol(0, 1 << 56),
            Err(KeyError::IndexTooLarge { index: 1 << 56 })
        );
        assert_eq!(symbol(52, 0), Err(KeyError::RobotOutOfRange { robot: 52 }));
        assert_eq!(robot_index(51), Ok(51));
        assert_eq!(
            robot_index(52),
            Err(KeyError::RobotOutOfRange { robot: 52 })
        );
        assert_eq!(
            robot_index(256 + 1),
            Err(KeyError::RobotOutOfRange { robot: 257 })
        );
        assert_eq!((robot(7), index(7)), (None, 7));
    }

    #[test]
    fn robots_past_z_are_upper_case_letters() {
        // distributed_mapper's 36- and 49-robot teams: file 26.g2o is robot 'A', 48 is 'W'.
        let a_upper = (u64::from(b'A') << 56) | 1234;
        assert_eq!((robot(a_upper), index(a_upper)), (Some(26), 1234));
        assert_eq!(symbol(26, 1234), Ok(a_upper));
        assert_eq!(label(symbol(48, 7).unwrap()), "W7");
        assert_eq!(robot_char(51), Ok('Z'));
        assert!(robot_char(52).is_err());
        // Every robot maps to a distinct character and back.
        for r in 0..MAX_ROBOTS {
            let c = robot_char(r).unwrap();
            assert_eq!(robot_of_char(c as u8), Some(r));
            let k = symbol(r, 99).unwrap();
            assert_eq!((robot(k), index(k)), (Some(r), 99));
            assert_eq!(label(k), format!("{c}99"));
        }
        // Other characters are not robots: a plain index, or a key of another scheme.
        for c in [b'0', b'[', b'`', b'{', b'@', 0xC1] {
            assert_eq!(robot_of_char(c), None);
            let k = (u64::from(c) << 56) | 5;
            assert_eq!(robot(k), None, "{c}");
        }
    }
}
