//! # doorslam-team
//!
//! The link between robots: Zenoh in peer-to-peer mode. Only compact, versioned messages
//! cross it (descriptors, keypoints for verification, relative poses, separator
//! estimates), and every byte goes through the bandwidth ledger.
//!
//! - [`link`]: Zenoh sessions and every key expression the team uses (the table is there).
//! - [`delivery`]: the delivery contract with one peer (in order, exactly once per kind,
//!   state superseding, sessions per epoch).
//! - [`protocol`]: the rendezvous protocol with one peer as a pure state machine, and the
//!   traits it calls into ([`DescriptorSource`], [`Verifier`], [`BackendExchange`]).
//! - [`node`]: one robot's end, over any [`Link`]; checks every incoming message (known
//!   peer, decodes, sender), counts it in the [`ledger`], routes it to its peer's session.
//! - [`seen`]: the bounded sets of ids already processed (a window above a rising floor).
//! - [`zenoh_link`]: the [`Link`] over Zenoh, with discovery by liveliness tokens.
//! - [`presence`]: the present peers, checked against liveliness queries (missed puts
//!   and deletes mended, a session whose tables lost a talking peer reopened).
//! - [`emulate`]: an in-process [`Link`] with loss and cuts, for tests.
//! - [`standin`]: simulated descriptors, a truth-table verifier, back-end stand-ins.
//! - [`bw`]: the bandwidth report (`doorslam bw`) from ledger files.
//! - [`runner`]: `doorslam service team` with the stand-ins.
//! - [`security`]: TLS with mutual authentication and access control of the team link.
//! - [`certs`]: the team CA and the robots' and routers' certificates (`doorslam team certs`).
//! - [`router`]: an embedded Zenoh router for large fleets (`doorslam router`).

pub mod bw;
pub mod certs;
pub mod delivery;
pub mod emulate;
pub mod ledger;
pub mod link;
pub mod node;
pub mod presence;
pub mod protocol;
pub mod router;
pub mod runner;
pub mod security;
pub mod seen;
pub mod standin;
pub mod zenoh_link;

pub use ledger::{Ledger, LedgerHandle};
pub use link::{key_expr, open_peer, LinkConfig, TeamError};
pub use node::{Link, LinkEvent, Node, Pieces};
pub use protocol::{BackendExchange, BackendRefusal, DescriptorSource, Identity, Verifier};

/// Re-exported so callers use the exact Zenoh this crate was built against.
pub use zenoh;
