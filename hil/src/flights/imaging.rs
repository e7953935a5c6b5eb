//! Imaging a planned team: every robot's frames through the ideal or the realistic camera.

use crate::render::{render_stereo, StereoPair};
use crate::sensor::{
    exposure_track, frame_noise_seed, render_realistic, CameraModel, ExposureMotion, FrameExposure,
};
use crate::world::World;

use super::{FlightError, TeamFlight};

/// Renders a team's frames with one camera model; with the realistic camera, each robot's
/// exposure track is computed once, here (both eyes of a frame share it).
#[derive(Debug)]
pub struct TeamCamera<'a> {
    world: &'a World,
    team: &'a TeamFlight,
    model: CameraModel,
    /// Per robot, per frame (empty for the ideal camera).
    tracks: Vec<Vec<FrameExposure>>,
}

impl<'a> TeamCamera<'a> {
    /// Checks the model against the team's frame rate (an exposure cannot outlast a frame).
    pub fn new(
        world: &'a World,
        team: &'a TeamFlight,
        model: CameraModel,
    ) -> Result<Self, FlightError> {
        let tracks = match &model {
            CameraModel::Ideal => Vec::new(),
            CameraModel::Realistic(sensor) => {
                sensor.validate(team.config.rate_hz)?;
                team.flights
                    .iter()
                    .enumerate()
                    .map(|(r, f)| exposure_track(sensor, team.config.seed, r, &f.times))
                    .collect()
            }
        };
        Ok(Self {
            world,
            team,
            model,
            tracks,
        })
    }

    pub fn model(&self) -> &CameraModel {
        &self.model
    }

    /// The realistic camera's exposure of a frame; `None` for the ideal camera or a frame
    /// that does not exist.
    pub fn exposure(&self, robot: usize, frame: usize) -> Option<&FrameExposure> {
        self.tracks.get(robot)?.get(frame)
    }

    /// The camera's motion during a frame's exposure (still for the ideal camera).
    pub fn motion(&self, robot: usize, frame: usize) -> Option<ExposureMotion> {
        let flight = self.team.flights.get(robot)?;
        let (t, pose) = (flight.times.get(frame)?, flight.poses.get(frame)?);
        Some(match self.exposure(robot, frame) {
            None => ExposureMotion::still(),
            Some(e) => {
                let half = 0.5 * e.exposure_s;
                ExposureMotion::from_poses(
                    pose,
                    &flight.pose_at(t - half),
                    &flight.pose_at(t + half),
                )
            }
        })
    }

    /// Robot `robot`'s stereo frame `frame`; `None` if it does not exist.
    pub fn render(&self, robot: usize, frame: usize) -> Result<Option<StereoPair>, FlightError> {
        let Some(pose) = self
            .team
            .flights
            .get(robot)
            .and_then(|f| f.poses.get(frame))
        else {
            return Ok(None);
        };
        let camera = &self.team.camera;
        let pair = match (
            &self.model,
            self.exposure(robot, frame),
            self.motion(robot, frame),
        ) {
            (CameraModel::Realistic(sensor), Some(exposure), Some(motion)) => {
                let seed = frame_noise_seed(self.team.config.seed, robot, frame);
                render_realistic(self.world, camera, sensor, pose, exposure, &motion, seed)?
            }
            _ => render_stereo(self.world, camera, pose),
        };
        Ok(Some(pair))
    }
}
