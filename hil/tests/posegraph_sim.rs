//! The multi-robot pose-graph simulator: determinism, outlier accounting, noise model,
//! correlated groups, dataset files, and PCM on its output.

use std::collections::BTreeSet;
use std::path::PathBuf;

use doorslam_backend::eval::{read_kitti, read_tum};
use doorslam_backend::outliers::{pairwise_mahalanobis2, Closure, Odometry, Pcm, Scope};
use doorslam_backend::robust::chi2_quantile;
use doorslam_backend::{read_g2o, Graph, UnknownTags};
use doorslam_geometry::key;
use doorslam_geometry::LieGroup;
use doorslam_hil::posegraph_sim::*;
use nalgebra::Isometry3;

/// A fresh scratch directory per test (no tempfile dev-dependency in this crate).
fn scratch_dir(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!(
        "doorslam-posegraph-sim-{}-{name}",
        std::process::id()
    ));
    let _ = std::fs::remove_dir_all(&dir);
    dir
}

fn chi2_999() -> f64 {
    chi2_quantile(0.999, 6).unwrap()
}

fn config(seed: u64, outlier_fraction: f64) -> SimConfig {
    SimConfig {
        seed,
        outlier_fraction,
        ..SimConfig::default()
    }
}

/// rᵀΩr of the closure's measurement against the truth (optionally b displaced by `w`).
fn closure_chi2(team: &SimulatedTeam, k: usize, w: Option<&Isometry3<f64>>) -> f64 {
    let (c, e) = (&team.closures[k], &team.closure_edges()[k]);
    let (ta, tb) = (
        team.true_pose(c.key_a).unwrap(),
        team.true_pose(c.key_b).unwrap(),
    );
    let t = match w {
        Some(w) => ta.inverse() * w * tb,
        None => ta.inverse() * tb,
    };
    measurement_chi2(&e.measured, &t, &e.information)
}

#[test]
fn same_seed_gives_identical_files_and_another_seed_differs() {
    let read_all = |dir: &PathBuf| {
        let mut names: Vec<_> = std::fs::read_dir(dir)
            .unwrap()
            .map(|e| e.unwrap().file_name())
            .collect();
        names.sort();
        names
            .into_iter()
            .map(|n| (n.clone(), std::fs::read(dir.join(n)).unwrap()))
            .collect::<Vec<_>>()
    };
    let cfg = SimConfig {
        outlier_fraction: 0.3,
        correlated_groups: 2,
        intra_closures: true,
        ..SimConfig::default()
    };
    let (d1, d2, d3) = (
        scratch_dir("det1"),
        scratch_dir("det2"),
        scratch_dir("det3"),
    );
    write_dataset(&simulate(&cfg).unwrap(), &d1).unwrap();
    write_dataset(&simulate(&cfg).unwrap(), &d2).unwrap();
    let other = SimConfig { seed: 2, ..cfg };
    write_dataset(&simulate(&other).unwrap(), &d3).unwrap();
    let (f1, f2, f3) = (read_all(&d1), read_all(&d2), read_all(&d3));
    assert_eq!(f1.len(), 1 + 2 * 5 + 1);
    assert_eq!(f1, f2, "same seed, same bytes");
    let g2o = |files: &[(std::ffi::OsString, Vec<u8>)]| {
        files
            .iter()
            .find(|(n, _)| n == "graph.g2o")
            .unwrap()
            .1
            .clone()
    };
    assert_ne!(g2o(&f1), g2o(&f3), "another seed, another graph");
    for d in [d1, d2, d3] {
        std::fs::remove_dir_all(d).unwrap();
    }
}

#[test]
fn changing_the_outlier_fraction_keeps_truth_and_inliers() {
    let a = simulate(&config(3, 0.0)).unwrap();
    let b = simulate(&config(3, 0.4)).unwrap();
    assert_eq!(a.truth, b.truth);
    let inliers = |t: &SimulatedTeam| -> Vec<_> {
        t.closures
            .iter()
            .zip(t.closure_edges())
            .filter(|(c, _)| c.inlier)
            .map(|(c, e)| (c.key_a, c.key_b, e.measured))
            .collect()
    };
    assert_eq!(inliers(&a), inliers(&b));
    assert_eq!(a.odometry_edges(), b.odometry_edges());
}

#[test]
fn default_config_gives_the_advertised_closure_counts() {
    for seed in 1..=10 {
        let team = simulate(&config(seed, 0.3)).unwrap();
        let c = team.counts();
        println!("seed {seed}: {c:?}");
        assert!(
            (25..=90).contains(&c.inter_inliers),
            "seed {seed}: {} inliers",
            c.inter_inliers
        );
        assert_eq!(c.correlated_outliers + c.intra_inliers, 0);
    }
}

#[test]
fn graph_layout_matches_the_labels() {
    let cfg = SimConfig {
        outlier_fraction: 0.3,
        correlated_groups: 2,
        intra_closures: true,
        ..SimConfig::default()
    };
    let team = simulate(&cfg).unwrap();
    let n = cfg.poses_per_robot;
    assert_eq!(team.graph.len(), cfg.robots * n);
    assert_eq!(team.odometry_edges().len(), cfg.robots * (n - 1));
    for (robot, poses) in team.truth.iter().enumerate() {
        let first = team
            .graph
            .index_of(key::symbol(robot as u8, 0).unwrap())
            .unwrap();
        assert_eq!(
            team.graph.poses()[first],
            poses[0],
            "chained from the true start"
        );
    }
    let keys = team.graph.keys();
    let mut pairs = BTreeSet::new();
    let mut last_arrival = 0;
    for (c, e) in team.closures.iter().zip(team.closure_edges()) {
        assert_eq!((keys[e.i], keys[e.j]), (c.key_a, c.key_b));
        assert!(pairs.insert((c.key_a, c.key_b)), "pose pairs are unique");
        let arrival = key::index(c.key_a).max(key::index(c.key_b));
        assert!(arrival >= last_arrival, "closures come in arrival order");
        last_arrival = arrival;
        if key::robot(c.key_a) == key::robot(c.key_b) {
            assert!(c.inlier && c.group.is_none());
            assert!(key::index(c.key_b) >= key::index(c.key_a) + 6, "a revisit");
        } else {
            assert!(key::robot(c.key_a) < key::robot(c.key_b));
        }
    }
    let counts = team.counts();
    println!("{counts:?}");
    assert!(counts.intra_inliers > 0);
    assert_eq!(counts.correlated_outliers, 2 * cfg.correlated_group_size);
}

#[test]
fn probability_one_closes_every_pair_within_the_radius() {
    let cfg = SimConfig {
        robots: 3,
        poses_per_robot: 80,
        closure_probability: 1.0,
        outlier_fraction: 0.0,
        intra_closures: true,
        seed: 9,
        ..SimConfig::default()
    };
    let team = simulate(&cfg).unwrap();
    // Brute force over all pose pairs (the simulator sweeps over x-sorted poses).
    let mut expected = BTreeSet::new();
    let min_gap = (2.0 * cfg.closure_radius_m / cfg.step_m).ceil() as usize;
    for (ra, pa) in team.truth.iter().enumerate() {
        for (rb, pb) in team.truth.iter().enumerate().skip(ra) {
            for (i, a) in pa.iter().enumerate() {
                for (j, b) in pb.iter().enumerate() {
                    let close =
                        (a.translation.vector - b.translation.vector).norm() < cfg.closure_radius_m;
                    let revisit = ra != rb || j >= i + min_gap;
                    if close && revisit {
                        expected.insert((
                            key::symbol(ra as u8, i as u64).unwrap(),
                            key::symbol(rb as u8, j as u64).unwrap(),
                        ));
                    }
                }
            }
        }
    }
    let got: BTreeSet<(u64, u64)> = team.closures.iter().map(|c| (c.key_a, c.key_b)).collect();
    assert!(expected.len() > 100);
    assert_eq!(got, expected);
}

#[test]
fn a_single_robot_gets_only_intra_closures() {
    let team = simulate(&SimConfig {
        robots: 1,
        intra_closures: true,
        closure_probability: 0.05,
        ..SimConfig::default()
    })
    .unwrap();
    let c = team.counts();
    assert!(c.intra_inliers > 0, "{c:?}");
    assert_eq!(
        c.inter_inliers + c.uniform_outliers + c.correlated_outliers,
        0
    );
    assert_eq!(team.outlier_fraction(), 0.0);
}

#[test]
fn truth_flies_in_the_arena_at_the_configured_step() {
    let team = simulate(&SimConfig {
        robots: 4,
        poses_per_robot: 500,
        step_m: 1.5,
        ..SimConfig::default()
    })
    .unwrap();
    for poses in &team.truth {
        for p in poses {
            assert!(in_arena(&p.translation.vector.into()), "{p:?}");
        }
        for w in poses.windows(2) {
            let d = (w[1].translation.vector - w[0].translation.vector).norm();
            assert!((d - 1.5).abs() < 1e-9, "step {d}");
        }
        let z: Vec<f64> = poses.iter().map(|p| p.translation.z).collect();
        let spread =
            z.iter().cloned().fold(f64::MIN, f64::max) - z.iter().cloned().fold(f64::MAX, f64::min);
        assert!(spread > 0.5, "some vertical motion");
    }
}

#[test]
fn outlier_fraction_is_as_configured() {
    for f in [0.0, 0.1, 0.3, 0.5, 0.8] {
        for seed in 1..=5 {
            let team = simulate(&config(seed, f)).unwrap();
            let c = team.counts();
            let outliers = c.uniform_outliers + c.correlated_outliers;
            let total = outliers + c.inter_inliers;
            let expected = (f * c.inter_inliers as f64 / (1.0 - f)).round() as usize;
            assert_eq!(outliers, expected, "f {f} seed {seed}");
            // Rounding the count by at most 1/2 moves the fraction by at most 1/(2·total).
            assert!(
                (team.outlier_fraction() - f).abs() <= 0.5 / total as f64 + 1e-12,
                "f {f} seed {seed}: {}",
                team.outlier_fraction()
            );
        }
    }
    // Correlated closures count toward the outliers; uniform ones fill the rest.
    let team = simulate(&SimConfig {
        correlated_groups: 3,
        ..config(1, 0.4)
    })
    .unwrap();
    let c = team.counts();
    assert_eq!(c.correlated_outliers, 15);
    assert_eq!(
        c.uniform_outliers + c.correlated_outliers,
        (0.4 * c.inter_inliers as f64 / 0.6).round() as usize
    );
}

#[test]
fn inlier_closures_agree_with_truth_and_outliers_do_not() {
    let mut inlier_chi2 = Vec::new();
    let mut outlier_chi2 = Vec::new();
    for seed in 1..=5 {
        let team = simulate(&SimConfig {
            intra_closures: true,
            ..config(seed, 0.3)
        })
        .unwrap();
        for k in 0..team.closures.len() {
            let d2 = closure_chi2(&team, k, None);
            if team.closures[k].inlier {
                inlier_chi2.push(d2);
            } else {
                outlier_chi2.push(d2);
            }
        }
    }
    let passing = inlier_chi2.iter().filter(|&&d| d < chi2_999()).count();
    println!(
        "{passing}/{} inliers below chi2_6(0.999); min outlier chi2 {:.3e} over {}",
        inlier_chi2.len(),
        outlier_chi2.iter().cloned().fold(f64::MAX, f64::min),
        outlier_chi2.len()
    );
    assert!(passing as f64 >= 0.99 * inlier_chi2.len() as f64);
    assert!(outlier_chi2.len() > 50);
    assert!(outlier_chi2.iter().all(|&d| d > 100.0 * chi2_999()));
}

#[test]
fn odometry_noise_agrees_with_its_information() {
    let team = simulate(&SimConfig {
        robots: 10,
        poses_per_robot: 300,
        seed: 11,
        ..SimConfig::default()
    })
    .unwrap();
    let keys = team.graph.keys();
    let mut sum = 0.0;
    // Whitened residual components: each should be N(0, 1).
    let (mut mean, mut second) = ([0.0; 6], [0.0; 6]);
    let edges = team.odometry_edges();
    for e in edges {
        let (ta, tb) = (
            team.true_pose(keys[e.i]).unwrap(),
            team.true_pose(keys[e.j]).unwrap(),
        );
        let r = (e.measured.inverse() * (ta.inverse() * tb)).log();
        sum += r.dot(&(e.information * r));
        for k in 0..6 {
            let w = r[k] * e.information[(k, k)].sqrt();
            mean[k] += w;
            second[k] += w * w;
        }
    }
    let n = edges.len() as f64;
    let mean_chi2 = sum / n;
    println!("mean odometry chi2 {mean_chi2:.3} over {n} edges");
    // χ²₆ has variance 12: the mean of ~3000 is 6 ± 0.06.
    assert!((mean_chi2 - 6.0).abs() < 0.5, "{mean_chi2}");
    for k in 0..6 {
        let (m, v) = (mean[k] / n, second[k] / n);
        assert!(m.abs() < 0.1, "component {k} mean {m}");
        assert!((v - 1.0).abs() < 0.1, "component {k} variance {v}");
    }
}

/// A PCM closure (with its covariance) from a closure edge of the team.
fn pcm_closure(team: &SimulatedTeam, k: usize) -> Closure {
    let (c, e) = (&team.closures[k], &team.closure_edges()[k]);
    Closure {
        u: c.key_a,
        v: c.key_b,
        measured: e.measured,
        covariance: e.information.try_inverse().unwrap(),
    }
}

#[test]
fn correlated_groups_agree_with_each_other_not_with_inliers() {
    let team = simulate(&SimConfig {
        correlated_groups: 4,
        correlated_group_size: 5,
        ..config(5, 0.3)
    })
    .unwrap();
    assert_eq!(team.groups.len(), 4);
    let odo = Odometry::from_graph(&team.graph).unwrap();
    let gamma = chi2_quantile(0.99, 6).unwrap();
    let (mut within, mut across) = (Vec::new(), Vec::new());
    for (g, group) in team.groups.iter().enumerate() {
        assert!(group.offset.rotation.angle() >= 0.3);
        let t = group.offset.translation.vector.norm();
        assert!((3.0..=10.0).contains(&t), "{t}");
        let members: Vec<usize> = (0..team.closures.len())
            .filter(|&k| team.closures[k].group == Some(g))
            .collect();
        assert_eq!(members.len(), 5);
        for &k in &members {
            let c = &team.closures[k];
            assert!(!c.inlier);
            assert_eq!(key::robot(c.key_a), Some(group.robot_a));
            assert_eq!(key::robot(c.key_b), Some(group.robot_b));
            // Consistent with the displaced truth, far from the truth.
            assert!(closure_chi2(&team, k, Some(&group.offset)) < chi2_999());
            assert!(closure_chi2(&team, k, None) > 100.0 * chi2_999());
        }
        // PCM's pairwise test: consistent inside the group ...
        for (x, &k1) in members.iter().enumerate() {
            for &k2 in &members[x + 1..] {
                let d2 =
                    pairwise_mahalanobis2(&odo, &pcm_closure(&team, k1), &pcm_closure(&team, k2));
                within.push(d2.unwrap());
            }
        }
        // ... and not with the inliers of the same robot pair.
        for k in 0..team.closures.len() {
            let c = &team.closures[k];
            let same_pair = (key::robot(c.key_a), key::robot(c.key_b))
                == (Some(group.robot_a), Some(group.robot_b));
            if c.inlier && same_pair {
                let d2 = pairwise_mahalanobis2(
                    &odo,
                    &pcm_closure(&team, members[0]),
                    &pcm_closure(&team, k),
                );
                across.push(d2.unwrap());
            }
        }
    }
    println!(
        "within groups: {} pairs, max d2 {:.2}; group vs inliers: {} pairs, min d2 {:.1} (gamma {gamma:.2})",
        within.len(),
        within.iter().cloned().fold(0.0, f64::max),
        across.len(),
        across.iter().cloned().fold(f64::MAX, f64::min)
    );
    // Consistent pairs are χ²₆: about 1 % exceed γ(0.99) by chance, none is far off.
    let passing = within.iter().filter(|&&d| d <= gamma).count();
    assert!(passing as f64 >= 0.9 * within.len() as f64);
    assert!(within
        .iter()
        .all(|&d| d <= chi2_quantile(0.9999, 6).unwrap()));
    assert!(!across.is_empty());
    assert!(across.iter().all(|&d| d > gamma));
}

#[test]
fn written_files_read_back() {
    let team = simulate(&SimConfig {
        correlated_groups: 1,
        ..config(4, 0.3)
    })
    .unwrap();
    let dir = scratch_dir("readback");
    write_dataset(&team, &dir).unwrap();
    let file = read_g2o(&dir.join("graph.g2o"), UnknownTags::Error).unwrap();
    let Graph::Se3(graph) = file.graph else {
        panic!("an SE(3) graph")
    };
    assert_eq!(graph.len(), team.graph.len());
    assert_eq!(graph.edges().len(), team.graph.edges().len());
    assert_eq!(graph.keys(), team.graph.keys());
    for (robot, poses) in team.truth.iter().enumerate() {
        let kitti = read_kitti(dir.join(truth_file_name(robot, "txt"))).unwrap();
        let tum = read_tum(dir.join(truth_file_name(robot, "tum"))).unwrap();
        assert_eq!(kitti.len(), poses.len());
        assert_eq!(tum.len(), poses.len());
        for (k, p) in poses.iter().enumerate() {
            for read in [&kitti.poses()[k], &tum.poses()[k]] {
                assert!(read.ominus(p).norm() < 1e-9, "robot {robot} pose {k}");
            }
            assert_eq!(tum.timestamps()[k], k as f64);
        }
    }
    let labels = std::fs::read_to_string(dir.join("labels.txt")).unwrap();
    let rows: Vec<Vec<i64>> = labels
        .lines()
        .filter(|l| !l.starts_with('#'))
        .map(|l| {
            l.split(' ')
                .map(|x| {
                    x.parse::<u64>()
                        .map_or_else(|_| x.parse().unwrap(), |v| v as i64)
                })
                .collect()
        })
        .collect();
    assert_eq!(rows.len(), team.closures.len());
    for (row, c) in rows.iter().zip(&team.closures) {
        assert_eq!(row.len(), 8);
        assert_eq!((row[0] as u64, row[1] as u64), (c.key_a, c.key_b));
        assert_eq!(row[2], i64::from(key::robot(c.key_a).unwrap()));
        assert_eq!(row[3] as u64, key::index(c.key_a));
        assert_eq!(row[4], i64::from(key::robot(c.key_b).unwrap()));
        assert_eq!(row[5] as u64, key::index(c.key_b));
        assert_eq!(row[6], i64::from(c.inlier));
        assert_eq!(row[7], c.group.map_or(-1, |g| g as i64));
    }
    std::fs::remove_dir_all(dir).unwrap();
}

#[test]
fn write_errors_name_the_path() {
    let team = simulate(&SimConfig {
        robots: 2,
        poses_per_robot: 5,
        ..SimConfig::default()
    })
    .unwrap();
    let dir = scratch_dir("blocked");
    std::fs::write(&dir, b"a file, not a directory").unwrap();
    let err = write_dataset(&team, &dir.join("sub")).unwrap_err();
    assert!(err.to_string().contains("blocked"), "{err}");
    std::fs::remove_file(dir).unwrap();
}

#[test]
fn bad_config_values_name_the_field() {
    type Edit = fn(&mut SimConfig);
    let cases: [(&str, Edit); 14] = [
        ("robots", |c| c.robots = 0),
        ("robots", |c| c.robots = 53),
        ("poses_per_robot", |c| c.poses_per_robot = 1),
        ("step_m", |c| c.step_m = 0.0),
        ("step_m", |c| c.step_m = f64::NAN),
        ("sigma_t", |c| c.sigma_t = -0.1),
        ("sigma_r", |c| c.sigma_r = 0.0),
        ("sigma_r", |c| c.sigma_r = 2.0),
        ("closure_radius_m", |c| c.closure_radius_m = f64::INFINITY),
        ("closure_probability", |c| c.closure_probability = 1.5),
        ("outlier_fraction", |c| c.outlier_fraction = 1.0),
        ("outlier_fraction", |c| c.outlier_fraction = -0.1),
        ("correlated_groups", |c| {
            c.robots = 1;
            c.correlated_groups = 1
        }),
        ("correlated_group_size", |c| {
            c.correlated_groups = 1;
            c.correlated_group_size = 0
        }),
    ];
    assert!(SimConfig::default().validate().is_ok());
    for (field, edit) in cases {
        let mut c = SimConfig::default();
        edit(&mut c);
        match simulate(&c) {
            Err(SimError::InvalidConfig { field: f, .. }) => assert_eq!(f, field),
            other => panic!(
                "{field}: expected an error, got {:?}",
                other.map(|t| t.counts())
            ),
        }
        assert!(c.validate().unwrap_err().to_string().contains(field));
    }
}

/// Runs PCM (p = 0.99, inter-robot) on the team; returns (kept inliers, kept uniform
/// outliers, kept correlated outliers).
fn pcm_kept(team: &SimulatedTeam) -> (usize, usize, usize) {
    let summary = Pcm::new(0.99, Scope::InterRobot)
        .unwrap()
        .run(&team.graph)
        .unwrap();
    assert!(summary.exact);
    let kept: BTreeSet<(u64, u64)> = summary.inliers.iter().copied().collect();
    assert_eq!(kept.len(), summary.clique_size);
    let count = |f: &dyn Fn(&LabelledClosure) -> bool| {
        team.closures
            .iter()
            .filter(|l| f(l) && kept.contains(&(l.key_a, l.key_b)))
            .count()
    };
    (
        count(&|l| l.inlier),
        count(&|l| !l.inlier && l.group.is_none()),
        count(&|l| l.group.is_some()),
    )
}

#[test]
fn pcm_rejects_every_uniform_outlier_and_keeps_most_inliers() {
    // Two drones, ~30 inliers, 30 % uniform outliers (the paper's ARGoS setting per pair).
    let (mut inliers, mut kept_inliers) = (0, 0);
    for seed in 1..=10 {
        let team = simulate(&SimConfig {
            robots: 2,
            closure_probability: 0.05,
            outlier_fraction: 0.3,
            seed,
            ..SimConfig::default()
        })
        .unwrap();
        let c = team.counts();
        let (ki, ko, _) = pcm_kept(&team);
        println!(
            "PCM p=0.99 seed {seed}: {} inliers, {} outliers -> kept {ki} inliers, {ko} outliers",
            c.inter_inliers, c.uniform_outliers
        );
        assert!(c.uniform_outliers > 0, "{c:?}");
        assert_eq!(ko, 0, "seed {seed}: an outlier survived");
        inliers += c.inter_inliers;
        kept_inliers += ki;
    }
    println!("PCM p=0.99 over 10 seeds: kept {kept_inliers} of {inliers} inliers, 0 outliers");
    assert!(kept_inliers as f64 >= 0.8 * inliers as f64);
}

#[test]
fn pcm_on_correlated_groups_is_reported() {
    // Groups of 5 consistent wrong closures against ~30 inliers per robot pair: the inlier
    // clique is larger, so PCM should still pick it; reported for the record.
    let (mut groups_kept, mut inliers, mut kept_inliers) = (0, 0, 0);
    for seed in 1..=10 {
        let team = simulate(&SimConfig {
            robots: 2,
            closure_probability: 0.05,
            outlier_fraction: 0.3,
            correlated_groups: 2,
            seed,
            ..SimConfig::default()
        })
        .unwrap();
        let c = team.counts();
        let (ki, ku, kc) = pcm_kept(&team);
        println!(
            "PCM p=0.99 seed {seed}: {c:?} -> kept {ki} inliers, {ku} uniform, {kc} correlated"
        );
        assert_eq!(ku, 0);
        groups_kept += kc;
        inliers += c.inter_inliers;
        kept_inliers += ki;
    }
    println!("correlated: kept {groups_kept} group closures, {kept_inliers} of {inliers} inliers");
    assert_eq!(groups_kept, 0);
}
