//! # doorslam-geometry
//!
//! The geometry every part of doorslam shares, defined once: the back-end's solver and PCM,
//! the front-end's PnP and keyframes, the team link's pose messages and the simulators all
//! use these types, so a convention (right perturbations, rotation-first tangents, the
//! multi-robot key layout, the information layout) cannot drift between them.
//!
//! - [`SO3`], [`SE3`], [`SE2`] and the [`LieGroup`] trait: `Exp`/`Log`, composition,
//!   inverse, adjoint, right Jacobians and their inverses;
//! - [`key`]: multi-robot keys (`robot_char << 56 | index`), refusing indices that alias;
//! - [`pose`]: the `[x y z qx qy qz qw]` layout, checked on the way in;
//! - [`information`]: the 21-value upper-triangle layout, the rules an information matrix
//!   must satisfy (finite, symmetric, positive definite), covariance conversions and the
//!   nearest positive-definite repair.
//!
//! A pure library on nalgebra: no I/O, no threads.

pub mod information;
pub mod key;
pub mod lie;
pub mod pose;
pub mod so3;

pub use information::{check_information, InformationCheck, InformationError};
pub use key::KeyError;
pub use lie::{
    inverse_action_jacobian, reverse_measurement, LieGroup, Tangent, TangentMatrix, SE2, SE3,
};
pub use pose::{pose_from_array, pose_to_array, PoseError};
pub use so3::{hat, project_so3, vee, SO3, UNIT_QUATERNION_TOLERANCE};
