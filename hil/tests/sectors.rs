//! The sector patrol plan (the demo's scenario), checked from ground truth for teams of 2
//! to 8 drones and several seeds: every drone flies at drone speed for 90 s, re-visits
//! places another drone saw (several crossings of others' routes, at different times) and
//! its own places, and meets another drone in flight; the default team has aliased
//! look-alikes too.

use doorslam_hil::flights::{
    closure_candidates, fly_team, overlap_counts, rendezvous_events, simulate_team, ClosureKind,
    FlightConfig, FlightPlan, FlightRole, RangeEventKind, MIN_MEETING_S, MIN_SEPARATION_M,
    SPEED_SPREAD,
};
use doorslam_hil::{StereoCamera, World};

/// The demo's defaults: 90 s at 10 Hz, the slowest drone at 5 m/s.
fn config(robots: usize, seed: u64) -> FlightConfig {
    FlightConfig {
        robots,
        frames: 900,
        speed_mps: 5.0,
        seed,
        plan: FlightPlan::Sectors,
        ..FlightConfig::default()
    }
}

#[test]
fn every_drone_revisits_places_of_others_and_its_own_and_meets_someone() {
    for robots in 2..=8 {
        for seed in 1..=4 {
            let world = World::town(seed);
            let config = config(robots, seed);
            let flights = fly_team(&world, &config).unwrap();
            let counts = overlap_counts(&flights);
            let events = rendezvous_events(&flights, config.radio_range_m);
            let what = format!("{robots} drones, seed {seed}");
            for (r, f) in flights.iter().enumerate() {
                // Drone speed and distance.
                assert!(
                    (config.speed_mps..=config.speed_mps * (1.0 + SPEED_SPREAD) + 1e-9)
                        .contains(&f.speed_mps),
                    "{what}: drone {r} at {} m/s",
                    f.speed_mps
                );
                let length: f64 = f
                    .poses
                    .windows(2)
                    .map(|w| {
                        (w[1].translation.vector - w[0].translation.vector)
                            .xy()
                            .norm()
                    })
                    .sum();
                assert!(length >= 400.0, "{what}: drone {r} flies {length} m");
                assert!(matches!(f.role, FlightRole::Patrol { .. }));
                // Places of others, several times, at different times; its own places.
                assert!(
                    counts.others_revisited(r) >= 1,
                    "{what}: drone {r} re-visits no place another drone saw: {:?}",
                    counts.revisits[r]
                );
                let crossings = &counts.crossings[r];
                assert!(
                    crossings.len() >= 2
                        && crossings[crossings.len() - 1].1 - crossings[0].1 >= 20.0,
                    "{what}: drone {r} crosses others' routes at {crossings:?} (drone, s)"
                );
                assert!(
                    counts.own_revisited(r) >= 1,
                    "{what}: drone {r} never re-visits its own places"
                );
                // Meets another drone in flight (in range long enough, not only at
                // take-off), and leaves again.
                let meets = events.iter().any(|e| {
                    e.kind == RangeEventKind::Enter
                        && e.time_s > 0.0
                        && (e.robot_a == r || e.robot_b == r)
                        && events.iter().any(|l| {
                            l.kind == RangeEventKind::Leave
                                && (l.robot_a, l.robot_b) == (e.robot_a, e.robot_b)
                                && l.time_s >= e.time_s + MIN_MEETING_S - 0.5
                        })
                });
                assert!(meets, "{what}: drone {r} meets nobody in flight");
            }
            // Never too close to each other.
            for a in 0..robots {
                for b in a + 1..robots {
                    for k in 0..config.frames {
                        let d = (flights[a].poses[k].translation.vector
                            - flights[b].poses[k].translation.vector)
                            .norm();
                        assert!(
                            d >= MIN_SEPARATION_M - 0.5,
                            "{what}: {a} and {b} {d} m apart at frame {k}"
                        );
                    }
                }
            }
        }
    }
}

#[test]
fn a_lone_drone_revisits_its_own_places() {
    let world = World::town(1);
    let flights = fly_team(&world, &config(1, 1)).unwrap();
    let counts = overlap_counts(&flights);
    assert!(counts.own_revisited(0) >= 1, "{counts:?}");
    assert!(counts.crossings[0].is_empty());
}

#[test]
fn the_default_team_sees_look_alikes_and_its_candidates_are_true() {
    let world = World::town(1);
    let config = config(3, 1);
    let team = simulate_team(&world, &StereoCamera::euroc_like(), &config).unwrap();
    let overlaps = team.count(ClosureKind::Overlap);
    let aliased = team.count(ClosureKind::Aliased);
    let counts = overlap_counts(&team.flights);
    for f in &team.flights {
        eprintln!("  {} at {:.2} m/s", f.role, f.speed_mps);
    }
    eprintln!(
        "default team: {overlaps} overlap, {aliased} aliased, {} own candidates, {} events; revisits {:?}, crossings {:?}",
        team.own.len(),
        team.events.len(),
        counts.revisits,
        counts.crossings
    );
    assert!(
        overlaps > 0 && aliased > 0,
        "{overlaps} overlap, {aliased} aliased"
    );
    // Own candidates: the later frame first, at least 20 s after the earlier one.
    assert!(team.own.iter().any(|c| c.kind == ClosureKind::Overlap));
    for c in &team.own {
        assert_eq!(c.robot_a, c.robot_b);
        let f = &team.flights[c.robot_a];
        assert!(
            f.times[c.frame_a] - f.times[c.frame_b] >= 20.0 - 1e-9,
            "{c:?}"
        );
    }
    assert_eq!(
        closure_candidates(&world, &team.camera, &team.flights),
        team.closures
    );
}
