//! rmw_zenoh's wire forms (its `docs/design.md`, Jazzy and later): the key expression a
//! topic's samples are put on, the liveliness tokens that make a node and its publishers
//! appear in the ROS 2 graph, the publisher GID and the attachment every sample carries.
//!
//! - data: `<domain_id>/<fully qualified topic without its leading slash>/<DDS type
//!   name>/<type hash>`;
//! - node token: `@ros2_lv/<domain_id>/<session id>/<node id>/<node id>/NN/<enclave>/
//!   <namespace>/<node name>`;
//! - publisher token: `@ros2_lv/<domain_id>/<session id>/<node id>/<entity id>/MP/<enclave>/
//!   <namespace>/<node name>/<topic>/<DDS type name>/<type hash>/<qos>`, names mangled
//!   (every `/` as `%`, an empty one as `%`), the QoS as rmw_zenoh's `qos_to_keyexpr`
//!   writes it (a field left empty where it equals rmw_zenoh's default);
//! - GID: XXH3-128 of the entity's whole token, low 64 bits then high 64 bits,
//!   little-endian (what rmw_zenoh hands to the RMW layer);
//! - attachment: sequence number (i64 LE), source timestamp (i64 LE, ns since the Unix
//!   epoch), the GID's length as one byte (16), the GID's 16 bytes.

use crate::types::TypeDef;
use crate::WireError;

/// The liveliness admin space, a Zenoh hermetic namespace.
pub const ADMIN_SPACE: &str = "@ros2_lv";
/// Bytes in a publisher GID.
pub const GID_LEN: usize = 16;
/// Bytes in a sample attachment.
pub const ATTACHMENT_LEN: usize = 8 + 8 + 1 + GID_LEN;

/// `rmw_qos_reliability_policy_e`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Reliability {
    Reliable = 1,
    BestEffort = 2,
}

/// `rmw_qos_durability_policy_e`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Durability {
    TransientLocal = 1,
    Volatile = 2,
}

/// `rmw_qos_history_policy_e`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum History {
    KeepLast = 1,
    KeepAll = 2,
}

/// The QoS a publisher states in its token. Deadline, lifespan and liveliness are always
/// rmw_zenoh's defaults (infinite, automatic): doorslam's publishers set none of them.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Qos {
    pub reliability: Reliability,
    pub durability: Durability,
    pub history: History,
    pub depth: u32,
}

impl Qos {
    /// rmw_zenoh's default profile (`RMW_ZENOH_DEFAULT_*`): reliable, volatile, keep last
    /// 42.
    pub const RMW_ZENOH_DEFAULT: Qos = Qos {
        reliability: Reliability::Reliable,
        durability: Durability::Volatile,
        history: History::KeepLast,
        depth: 42,
    };

    /// What rclcpp's `QoS(depth)` gives: reliable, volatile, keep last `depth`.
    pub const fn keep_last(depth: u32) -> Qos {
        Qos {
            depth,
            ..Self::RMW_ZENOH_DEFAULT
        }
    }

    /// The token's QoS part: `reliability:durability:history,depth:deadline_s,deadline_ns:
    /// lifespan_s,lifespan_ns:liveliness,lease_s,lease_ns`, each value empty when it is
    /// the default.
    pub fn keyexpr(&self) -> String {
        let d = Self::RMW_ZENOH_DEFAULT;
        let part = |differs: bool, v: u32| {
            if differs {
                v.to_string()
            } else {
                String::new()
            }
        };
        format!(
            "{}:{}:{},{}:,:,:,,",
            part(self.reliability != d.reliability, self.reliability as u32),
            part(self.durability != d.durability, self.durability as u32),
            part(self.history != d.history, self.history as u32),
            part(self.depth != d.depth, self.depth),
        )
    }
}

/// Checks a ROS name (node name, namespace, topic): letters, digits, `_` and `/`
/// separators, nothing that Zenoh would read as a wildcard or a chunk of its own.
fn check_name(what: &'static str, name: &str, slashes: bool) -> Result<(), WireError> {
    let allowed = |c: char| c.is_ascii_alphanumeric() || c == '_' || (slashes && c == '/');
    let trailing_slash = slashes && name.len() > 1 && name.ends_with('/');
    let ok =
        !name.is_empty() && name.chars().all(allowed) && !name.contains("//") && !trailing_slash;
    if ok {
        Ok(())
    } else {
        Err(WireError::InvalidName {
            what,
            name: name.to_string(),
        })
    }
}

/// `/` → `%` (an empty name → `%`).
pub fn mangle(name: &str) -> String {
    if name.is_empty() {
        "%".into()
    } else {
        name.replace('/', "%")
    }
}

/// A ROS 2 node as rmw_zenoh announces it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Node {
    pub domain_id: u32,
    /// The Zenoh session id, as Zenoh prints it (lowercase hex).
    pub session_id: String,
    /// The node's id within its context (rmw_zenoh counts from 0).
    pub node_id: u64,
    /// `/` or `/<ns>...`.
    pub namespace: String,
    pub name: String,
}

impl Node {
    /// A node; namespace `""` means the root (`/`).
    pub fn new(
        domain_id: u32,
        session_id: &str,
        node_id: u64,
        namespace: &str,
        name: &str,
    ) -> Result<Self, WireError> {
        let namespace = if namespace.is_empty() {
            "/".to_string()
        } else {
            namespace.to_string()
        };
        check_name("namespace", &namespace, true)?;
        if !namespace.starts_with('/') {
            return Err(WireError::InvalidName {
                what: "namespace",
                name: namespace,
            });
        }
        check_name("node name", name, false)?;
        if session_id.is_empty() || !session_id.chars().all(|c| c.is_ascii_hexdigit()) {
            return Err(WireError::InvalidName {
                what: "session id",
                name: session_id.to_string(),
            });
        }
        Ok(Self {
            domain_id,
            session_id: session_id.to_string(),
            node_id,
            namespace,
            name: name.to_string(),
        })
    }

    /// The namespace as a token part: `/` → `%`, `/a` → `%a`.
    fn namespace_part(&self) -> String {
        mangle(&self.namespace)
    }

    /// The node's `NN` token (no SROS enclave: `%`).
    pub fn token(&self) -> String {
        format!(
            "{ADMIN_SPACE}/{}/{}/{}/{}/NN/%/{}/{}",
            self.domain_id,
            self.session_id,
            self.node_id,
            self.node_id,
            self.namespace_part(),
            self.name
        )
    }

    /// A topic's fully qualified name: absolute names stay, relative ones go under the
    /// node's namespace.
    pub fn qualify(&self, topic: &str) -> Result<String, WireError> {
        let full = if topic.starts_with('/') {
            topic.to_string()
        } else if self.namespace == "/" {
            format!("/{topic}")
        } else {
            format!("{}/{topic}", self.namespace)
        };
        check_name("topic", &full, true)?;
        if full == "/" {
            return Err(WireError::InvalidName {
                what: "topic",
                name: topic.to_string(),
            });
        }
        Ok(full)
    }

    /// A publisher of `topic` (relative names under the node's namespace).
    pub fn publisher(
        &self,
        entity_id: u64,
        topic: &str,
        ty: &'static TypeDef,
        qos: Qos,
    ) -> Result<Publisher, WireError> {
        let topic = self.qualify(topic)?;
        let hash = ty.type_hash();
        let dds = ty.dds_name();
        let key = format!("{}/{}/{dds}/{hash}", self.domain_id, &topic[1..]);
        let token = format!(
            "{ADMIN_SPACE}/{}/{}/{}/{entity_id}/MP/%/{}/{}/{}/{dds}/{hash}/{}",
            self.domain_id,
            self.session_id,
            self.node_id,
            self.namespace_part(),
            self.name,
            mangle(&topic),
            qos.keyexpr()
        );
        let gid = gid(&token);
        Ok(Publisher {
            topic,
            key,
            token,
            gid,
        })
    }
}

/// What one ROS 2 publisher puts on Zenoh.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Publisher {
    /// Fully qualified topic name.
    pub topic: String,
    /// The key expression of its samples.
    pub key: String,
    /// Its `MP` liveliness token.
    pub token: String,
    pub gid: [u8; GID_LEN],
}

impl Publisher {
    /// The attachment of one sample.
    pub fn attachment(&self, sequence_number: i64, source_timestamp_ns: i64) -> Attachment {
        Attachment {
            sequence_number,
            source_timestamp_ns,
            gid: self.gid,
        }
    }
}

/// An entity's GID: XXH3-128 of its liveliness token.
pub fn gid(token: &str) -> [u8; GID_LEN] {
    let h = xxhash_rust::xxh3::xxh3_128(token.as_bytes());
    let mut out = [0u8; GID_LEN];
    out[..8].copy_from_slice(&(h as u64).to_le_bytes());
    out[8..].copy_from_slice(&((h >> 64) as u64).to_le_bytes());
    out
}

/// The attachment of one sample.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Attachment {
    pub sequence_number: i64,
    /// Nanoseconds since the Unix epoch.
    pub source_timestamp_ns: i64,
    pub gid: [u8; GID_LEN],
}

impl Attachment {
    pub fn encode(&self) -> [u8; ATTACHMENT_LEN] {
        let mut out = [0u8; ATTACHMENT_LEN];
        out[..8].copy_from_slice(&self.sequence_number.to_le_bytes());
        out[8..16].copy_from_slice(&self.source_timestamp_ns.to_le_bytes());
        out[16] = GID_LEN as u8;
        out[17..].copy_from_slice(&self.gid);
        out
    }

    pub fn decode(bytes: &[u8]) -> Result<Self, WireError> {
        let bad = |reason: &str| WireError::Attachment(format!("{reason} ({} bytes)", bytes.len()));
        if bytes.len() != ATTACHMENT_LEN {
            return Err(bad("not 33 bytes"));
        }
        if usize::from(bytes[16]) != GID_LEN {
            return Err(bad("GID length is not 16"));
        }
        let i64_at = |at: usize| {
            let mut b = [0u8; 8];
            b.copy_from_slice(&bytes[at..at + 8]);
            i64::from_le_bytes(b)
        };
        let mut gid = [0u8; GID_LEN];
        gid.copy_from_slice(&bytes[17..]);
        Ok(Self {
            sequence_number: i64_at(0),
            source_timestamp_ns: i64_at(8),
            gid,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::types::PATH;

    #[test]
    fn qos_parts_match_rmw_zenoh_design_examples() {
        // design.md: the talker's publisher (depth 7) and the listener's subscription (10).
        assert_eq!(Qos::keep_last(7).keyexpr(), "::,7:,:,:,,");
        assert_eq!(Qos::keep_last(10).keyexpr(), "::,10:,:,:,,");
        assert_eq!(Qos::RMW_ZENOH_DEFAULT.keyexpr(), "::,:,:,:,,");
        let q = Qos {
            reliability: Reliability::BestEffort,
            durability: Durability::TransientLocal,
            history: History::KeepLast,
            depth: 1,
        };
        assert_eq!(q.keyexpr(), "2:1:,1:,:,:,,");
    }

    #[test]
    fn node_and_publisher_forms() {
        let n = Node::new(3, "8b20917502ee955ac4476e0266340d5c", 0, "/a", "doorslam").unwrap();
        assert_eq!(
            n.token(),
            "@ros2_lv/3/8b20917502ee955ac4476e0266340d5c/0/0/NN/%/%a/doorslam"
        );
        let p = n
            .publisher(4, "team_path", &PATH, Qos::keep_last(10))
            .unwrap();
        let hash = PATH.type_hash();
        assert_eq!(p.topic, "/a/team_path");
        assert_eq!(
            p.key,
            format!("3/a/team_path/nav_msgs::msg::dds_::Path_/{hash}")
        );
        assert_eq!(
            p.token,
            format!(
                "@ros2_lv/3/8b20917502ee955ac4476e0266340d5c/0/4/MP/%/%a/doorslam/%a%team_path/\
                 nav_msgs::msg::dds_::Path_/{hash}/::,10:,:,:,,"
            )
        );
        // An absolute topic stays where it is; the root namespace is `%`.
        let root = Node::new(0, "ab", 1, "", "n").unwrap();
        assert!(root.token().ends_with("/1/1/NN/%/%/n"));
        let tf = root.publisher(2, "/tf", &PATH, Qos::keep_last(10)).unwrap();
        assert!(tf.key.starts_with("0/tf/"));
        assert!(tf.token.contains("/n/%tf/"));
    }

    #[test]
    fn bad_names_are_errors_naming_the_input() {
        for (ns, name) in [
            ("a", "n"),
            ("/a/", "n"),
            ("/a", "x/y"),
            ("/a*", "n"),
            ("/a", ""),
        ] {
            let e = Node::new(0, "ab", 0, ns, name).unwrap_err();
            assert!(matches!(e, WireError::InvalidName { .. }), "{ns} {name}");
        }
        assert!(Node::new(0, "not hex", 0, "/a", "n").is_err());
        let n = Node::new(0, "ab", 0, "/a", "n").unwrap();
        assert!(n.publisher(1, "b/**", &PATH, Qos::keep_last(1)).is_err());
    }

    #[test]
    fn attachment_round_trips_and_checks_its_layout() {
        let a = Attachment {
            sequence_number: 5,
            source_timestamp_ns: -1,
            gid: [7; GID_LEN],
        };
        let b = a.encode();
        assert_eq!(&b[..8], &[5, 0, 0, 0, 0, 0, 0, 0]);
        assert_eq!(&b[8..16], &[0xff; 8]);
        assert_eq!(b[16], 16);
        assert_eq!(Attachment::decode(&b).unwrap(), a);
        assert!(Attachment::decode(&b[..32]).is_err());
        let mut c = b;
        c[16] = 8;
        assert!(Attachment::decode(&c).is_err());
    }
}
