//! Maximum clique for PCM: the exact solver against brute force, the heuristic, warm starts,
//! time budgets, and a 1,000-closure PCM-like graph.

use std::time::{Duration, Instant};

use doorslam_backend::outliers::{
    core_decomposition, heuristic_clique, maximum_clique, CliqueOptions, ConsistencyGraph,
};
use proptest::prelude::*;

/// xorshift64*: deterministic graphs without a `rand` dependency.
struct XorShift(u64);

impl XorShift {
    fn next_u64(&mut self) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.wrapping_mul(0x2545_f491_4f6c_dd1d)
    }

    fn uniform(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }
}

fn random_graph(n: usize, p: f64, seed: u64) -> ConsistencyGraph {
    let mut rng = XorShift(seed | 1);
    let mut g = ConsistencyGraph::new(n);
    for a in 0..n {
        for b in a + 1..n {
            if rng.uniform() < p {
                g.add_edge(a, b).unwrap();
            }
        }
    }
    g
}

/// Size of the maximum clique over all 2^n subsets: `is_clique[s]` from `s` minus its
/// lowest vertex v, which must be a subset of v's neighbours.
fn brute_force_size(g: &ConsistencyGraph) -> usize {
    let n = g.len();
    assert!(n <= 20);
    let nbr: Vec<u32> = g
        .vertices()
        .map(|v| g.neighbors(v).map(|u| 1u32 << u).sum())
        .collect();
    let mut is_clique = vec![false; 1 << n];
    is_clique[0] = true;
    let mut best = 0;
    for s in 1u32..(1 << n) {
        let v = s.trailing_zeros() as usize;
        let rest = s & (s - 1);
        if is_clique[rest as usize] && rest & !nbr[v] == 0 {
            is_clique[s as usize] = true;
            best = best.max(s.count_ones() as usize);
        }
    }
    best
}

/// Core numbers by the definition: v is in the k-core if it survives repeatedly deleting
/// vertices of degree < k.
fn naive_core_numbers(g: &ConsistencyGraph) -> Vec<usize> {
    let mut core = vec![0; g.len()];
    for k in 1..g.len() {
        let mut alive: Vec<bool> = vec![true; g.len()];
        loop {
            let dead: Vec<usize> = g
                .vertices()
                .filter(|&v| alive[v] && g.neighbors(v).filter(|&u| alive[u]).count() < k)
                .collect();
            if dead.is_empty() {
                break;
            }
            for v in dead {
                alive[v] = false;
            }
        }
        for v in g.vertices().filter(|&v| alive[v]) {
            core[v] = k;
        }
    }
    core
}

fn exact(g: &ConsistencyGraph) -> doorslam_backend::outliers::CliqueResult {
    maximum_clique(g, &CliqueOptions::default())
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(512))]

    #[test]
    fn exact_matches_brute_force(n in 0usize..=18, p in 0.1f64..0.9, seed in any::<u64>()) {
        let g = random_graph(n, p, seed);
        let r = exact(&g);
        prop_assert!(r.exact);
        prop_assert!(g.is_clique(&r.vertices));
        prop_assert!(r.vertices.windows(2).all(|w| w[0] < w[1]));
        prop_assert_eq!(r.vertices.len(), brute_force_size(&g));
    }

    #[test]
    fn heuristic_returns_a_maximal_clique(n in 0usize..=18, p in 0.1f64..0.9, seed in any::<u64>()) {
        let g = random_graph(n, p, seed);
        let h = heuristic_clique(&g);
        prop_assert!(g.is_clique(&h));
        prop_assert!(h.len() <= brute_force_size(&g));
        // Maximal: no vertex outside it is joined to all of it.
        prop_assert!(g.vertices().all(|v| h.contains(&v) || !h.iter().all(|&u| g.has_edge(u, v))));
    }

    #[test]
    fn warm_start_gives_the_same_size(n in 0usize..=18, p in 0.1f64..0.9, seed in any::<u64>()) {
        let g = random_graph(n, p, seed);
        let cold = exact(&g);
        for initial in [cold.vertices.clone(), heuristic_clique(&g), (0..n).collect()] {
            let warm = maximum_clique(&g, &CliqueOptions { initial: Some(initial), ..Default::default() });
            prop_assert!(warm.exact);
            prop_assert!(g.is_clique(&warm.vertices));
            prop_assert_eq!(warm.vertices.len(), cold.vertices.len());
        }
    }

    #[test]
    fn zero_budget_returns_a_valid_clique(n in 0usize..=18, p in 0.1f64..0.9, seed in any::<u64>()) {
        let g = random_graph(n, p, seed);
        let r = maximum_clique(&g, &CliqueOptions { time_budget: Some(Duration::ZERO), ..Default::default() });
        prop_assert!(g.is_clique(&r.vertices));
        // Exact only when the core-number bound proves the seed clique without any search.
        prop_assert!(!r.exact || r.nodes_explored == 0);
        prop_assert!(!r.exact || r.vertices.len() == brute_force_size(&g));
    }

    #[test]
    fn core_numbers_match_definition(n in 0usize..=18, p in 0.1f64..0.9, seed in any::<u64>()) {
        let g = random_graph(n, p, seed);
        let cores = core_decomposition(&g);
        prop_assert_eq!(&cores.core_numbers, &naive_core_numbers(&g));
        let mut sorted = cores.peel_order.clone();
        sorted.sort_unstable();
        prop_assert_eq!(sorted, (0..n).collect::<Vec<_>>());
        let along: Vec<usize> = cores.peel_order.iter().map(|&v| cores.core_numbers[v]).collect();
        prop_assert!(along.windows(2).all(|w| w[0] <= w[1]));
    }
}

#[test]
fn empty_single_edgeless_and_complete_graphs() {
    let r = exact(&ConsistencyGraph::new(0));
    assert_eq!((r.vertices, r.exact), (vec![], true));
    assert!(heuristic_clique(&ConsistencyGraph::new(0)).is_empty());
    assert_eq!(
        core_decomposition(&ConsistencyGraph::new(0)).degeneracy(),
        0
    );

    let r = exact(&ConsistencyGraph::new(1));
    assert_eq!((r.vertices, r.exact), (vec![0], true));

    let r = exact(&ConsistencyGraph::new(7));
    assert_eq!(
        (r.vertices, r.exact),
        (vec![0], true),
        "ties go to the lowest index"
    );

    let complete = random_graph(70, 1.0, 3);
    assert_eq!(complete.edge_count(), 70 * 69 / 2);
    let r = exact(&complete);
    assert_eq!((r.vertices, r.exact), ((0..70).collect(), true));
    assert_eq!(r.nodes_explored, 0, "the core bound alone proves it");
}

#[test]
fn zero_budget_on_a_graph_that_needs_search_is_not_exact() {
    // A 5-cycle: every core number is 2, so the bound never proves the 2-clique.
    let mut g = ConsistencyGraph::new(5);
    for v in 0..5 {
        g.add_edge(v, (v + 1) % 5).unwrap();
    }
    let budget = CliqueOptions {
        time_budget: Some(Duration::ZERO),
        ..Default::default()
    };
    let r = maximum_clique(&g, &budget);
    assert!(!r.exact);
    assert_eq!(r.vertices.len(), 2);
    assert!(g.is_clique(&r.vertices));
    assert!(exact(&g).exact);
}

#[test]
fn edges_are_checked_and_symmetric() {
    let mut g = ConsistencyGraph::new(3);
    assert_eq!(g.add_edge(0, 2), Ok(true));
    assert_eq!(g.add_edge(2, 0), Ok(false));
    assert_eq!(g.add_edge(1, 1), Ok(false), "self loops are implicit");
    let err = g.add_edge(0, 3).unwrap_err();
    assert_eq!((err.vertex, err.len), (3, 3));
    assert!(g.has_edge(2, 0) && !g.has_edge(1, 1) && !g.has_edge(0, 9));
    assert_eq!((g.degree(0), g.degree(1), g.degree(9)), (1, 0, 0));
    assert_eq!(g.neighbors(2).collect::<Vec<_>>(), vec![0]);
}

#[test]
fn growing_across_word_boundaries_keeps_edges() {
    let mut g = ConsistencyGraph::new(0);
    for v in 0..200 {
        assert_eq!(g.add_vertex(), v);
        for u in (0..v).filter(|u| (u + v) % 3 != 0) {
            g.add_edge(u, v).unwrap();
        }
    }
    assert_eq!(g.vertices(), 0..200);
    for a in 0..200 {
        for b in 0..200 {
            assert_eq!(g.has_edge(a, b), a != b && (a + b) % 3 != 0, "{a}-{b}");
        }
    }
}

#[test]
fn stale_warm_start_is_repaired() {
    let g = random_graph(16, 0.6, 11);
    let best = exact(&g).vertices.len();
    // Out-of-range, duplicate and mutually inconsistent vertices are dropped, not trusted.
    let initial = vec![99, 3, 3, 4, 5, 6, 7, 8, 0];
    let r = maximum_clique(
        &g,
        &CliqueOptions {
            initial: Some(initial),
            ..Default::default()
        },
    );
    assert!(r.exact && g.is_clique(&r.vertices));
    assert_eq!(r.vertices.len(), best);
}

#[test]
fn incremental_growth_with_warm_start_matches_cold_solve() {
    let full = random_graph(120, 0.5, 5);
    let mut g = ConsistencyGraph::new(0);
    let mut previous = Vec::new();
    for v in 0..120 {
        g.add_vertex();
        for u in full.neighbors(v).filter(|&u| u < v) {
            g.add_edge(u, v).unwrap();
        }
        if v % 20 == 19 {
            let mut initial = previous.clone();
            initial.push(v);
            let warm = maximum_clique(
                &g,
                &CliqueOptions {
                    initial: Some(initial),
                    ..Default::default()
                },
            );
            let cold = exact(&g);
            assert!(warm.exact && g.is_clique(&warm.vertices));
            assert_eq!(warm.vertices.len(), cold.vertices.len());
            previous = warm.vertices;
        }
    }
}

#[test]
fn deterministic() {
    let g = random_graph(150, 0.6, 21);
    let a = exact(&g);
    let b = exact(&g);
    assert_eq!(a, b);
    assert_eq!(heuristic_clique(&g), heuristic_clique(&g));
}

/// Shuffled labels: 700 inliers then 300 outliers, so the index order gives nothing away.
fn shuffled_inliers(rng: &mut XorShift) -> Vec<bool> {
    let mut inlier: Vec<bool> = (0..1000).map(|i| i < 700).collect();
    for i in (1..inlier.len()).rev() {
        inlier.swap(i, (rng.next_u64() % (i as u64 + 1)) as usize);
    }
    inlier
}

fn gaussian(rng: &mut XorShift) -> f64 {
    let u = rng.uniform().max(f64::MIN_POSITIVE);
    (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * rng.uniform()).cos()
}

/// 1,000 closures as PCM sees them: each inlier carries a whitened 6-DoF error e_i ~ N(0, I),
/// and two inliers are consistent when their cycle error passes the chi-squared gate,
/// |e_i - e_j|² / 2 ≤ χ²₆(0.99) = 16.812 (about 99% of inlier pairs, failures concentrated
/// on the noisiest closures as in real PCM); 300 outliers are consistent with anything with
/// independent probability 0.05.
fn pcm_like_graph(seed: u64) -> (ConsistencyGraph, Vec<bool>) {
    let mut rng = XorShift(seed);
    let inlier = shuffled_inliers(&mut rng);
    let err: Vec<[f64; 6]> = (0..inlier.len())
        .map(|_| std::array::from_fn(|_| gaussian(&mut rng)))
        .collect();
    let mut g = ConsistencyGraph::new(inlier.len());
    for a in g.vertices() {
        for b in a + 1..g.len() {
            let consistent = if inlier[a] && inlier[b] {
                let d2: f64 = err[a]
                    .iter()
                    .zip(&err[b])
                    .map(|(x, y)| (x - y).powi(2))
                    .sum();
                d2 / 2.0 <= 16.812
            } else {
                rng.uniform() < 0.05
            };
            if consistent {
                g.add_edge(a, b).unwrap();
            }
        }
    }
    (g, inlier)
}

#[test]
fn thousand_vertex_pcm_like_graph_is_solved_exactly() {
    let (g, inlier) = pcm_like_graph(0x5eed_cafe);
    let t = Instant::now();
    let r = exact(&g);
    let cold = t.elapsed();
    eprintln!(
        "1000-vertex PCM-like graph ({} edges): clique {} exact {} nodes {} in {cold:?}",
        g.edge_count(),
        r.vertices.len(),
        r.exact,
        r.nodes_explored
    );
    assert!(r.exact);
    assert!(r.vertices.len() >= 600, "clique of {}", r.vertices.len());
    assert!(g.is_clique(&r.vertices));
    assert!(r.vertices.iter().all(|&v| inlier[v]), "an outlier was kept");

    // Incremental PCM: the previous clique as warm start.
    let t = Instant::now();
    let warm = maximum_clique(
        &g,
        &CliqueOptions {
            initial: Some(r.vertices.clone()),
            ..Default::default()
        },
    );
    eprintln!(
        "  warm start: nodes {} in {:?}",
        warm.nodes_explored,
        t.elapsed()
    );
    assert!(warm.exact);
    assert_eq!(
        warm.vertices, r.vertices,
        "an optimal warm start is kept as is"
    );
}

/// Inliers failing independently with probability 0.05 per pair make the inlier block a
/// dense random graph G(700, 0.95): its maximum clique is under 100 and proving it is far
/// beyond any branch and bound (the DIMACS-hard regime). The budget must still return the
/// heuristic's clique or better.
#[test]
fn dense_random_inliers_within_a_budget_return_a_valid_clique() {
    let mut rng = XorShift(0x5eed);
    let inlier = shuffled_inliers(&mut rng);
    let mut g = ConsistencyGraph::new(inlier.len());
    for a in g.vertices() {
        for b in a + 1..g.len() {
            let p = if inlier[a] && inlier[b] { 0.95 } else { 0.05 };
            if rng.uniform() < p {
                g.add_edge(a, b).unwrap();
            }
        }
    }
    let t = Instant::now();
    let r = maximum_clique(
        &g,
        &CliqueOptions {
            time_budget: Some(Duration::from_millis(200)),
            ..Default::default()
        },
    );
    eprintln!(
        "G(700, 0.95) + 300 outliers, 200 ms budget: clique {} exact {} nodes {} in {:?}",
        r.vertices.len(),
        r.exact,
        r.nodes_explored,
        t.elapsed()
    );
    assert!(g.is_clique(&r.vertices));
    assert!(r.vertices.len() >= heuristic_clique(&g).len());
}
