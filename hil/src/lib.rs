//! # doorslam-hil
//!
//! Hardware-in-the-loop and simulation: dataset replay into the iceoryx2 pipeline, the
//! synthetic stereo world renderer, multi-drone flights and the multi-robot pose-graph
//! simulator (issues "HIL/simulation" and "PCM"). Nothing has landed here yet; the
//! crate exists so the workspace layout and the `doorslam sim|replay` wiring are fixed.
