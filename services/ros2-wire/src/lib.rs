//! ROS 2 wire forms without ROS: the CDR payloads of the messages doorslam publishes
//! ([`msgs`], [`cdr`]), their RIHS01 type hashes and `ros2msg` schema texts ([`types`]),
//! and rmw_zenoh's key expressions, liveliness tokens, GIDs and sample attachments
//! ([`rmw`]). Pure functions of their inputs: no Zenoh session here, so the run record
//! (`run.mcap`) and the live publishers share one encoding.

pub mod cdr;
pub mod msgs;
pub mod rmw;
pub mod types;

pub use msgs::RosMessage;
pub use types::TypeDef;

/// What cannot be put on the wire; each names the offending input.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum WireError {
    #[error("a string in a ROS message cannot hold a NUL: {0:?}")]
    NulInString(String),
    #[error("a sequence of {len} elements does not fit CDR's u32 length")]
    TooLong { len: usize },
    #[error("invalid ROS {what} {name:?}: letters, digits, '_' and '/' separators only")]
    InvalidName { what: &'static str, name: String },
    #[error("rmw_zenoh attachment: {0}")]
    Attachment(String),
}
