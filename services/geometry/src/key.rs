//! Multi-robot keys, GTSAM's convention: `key = (robot_char << 56) | index`, robot 0 = `'a'`.
//!
//! A key names one pose of one robot across the whole team, so it travels in files (g2o),
//! messages and journals. Indices must fit in 56 bits: a larger one would silently alias
//! another robot's pose, so [`symbol`] refuses it.

/// Indices are the low 56 bits of a key.
pub const INDEX_BITS: u32 = 56;
/// The largest per-robot index a key can hold.
pub const MAX_INDEX: u64 = (1 << INDEX_BITS) - 1;
/// Robots are letters `'a'..='z'`.
pub const MAX_ROBOTS: u8 = 26;

/// A key that cannot be built.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum KeyError {
    #[error("pose index {index} does not fit in a multi-robot key (at most 2^56 - 1)")]
    IndexTooLarge { index: u64 },
    #[error("robot {robot} out of range (a key holds robots 0..{MAX_ROBOTS}, 'a'..'z')")]
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

/// The key of pose `index` of robot `robot` (0 = 'a', 1 = 'b', ...).
pub fn symbol(robot: u8, index: u64) -> Result<u64, KeyError> {
    let robot = robot_index(robot.into())?;
    if index > MAX_INDEX {
        return Err(KeyError::IndexTooLarge { index });
    }
    Ok(((b'a' + robot) as u64) << INDEX_BITS | index)
}

/// The robot (0 = 'a') of a multi-robot key, or `None` for a plain single-robot index.
pub fn robot(key: u64) -> Option<u8> {
    let c = (key >> INDEX_BITS) as u8;
    c.is_ascii_lowercase().then(|| c - b'a')
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
    match robot(key) {
        Some(r) => format!("{}{}", (b'a' + r) as char, index(key)),
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
        assert_eq!(symbol(26, 0), Err(KeyError::RobotOutOfRange { robot: 26 }));
        assert_eq!(robot_index(25), Ok(25));
        assert_eq!(
            robot_index(256 + 1),
            Err(KeyError::RobotOutOfRange { robot: 257 })
        );
        assert_eq!((robot(7), index(7)), (None, 7));
    }
}
