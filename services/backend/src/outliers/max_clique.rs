//! Maximum clique of a pairwise-consistency graph, the combinatorial core of PCM
//! (Mangelson et al., "Pairwise Consistency Maximization", ICRA 2018).
//!
//! PCM keeps the largest set of loop closures that are pairwise consistent: the maximum
//! clique of the graph whose vertices are closures and whose edges join consistent pairs.
//! Three pieces, all deterministic (no hashing; ties lean to the lower vertex index, though
//! the clique returned is not promised to be the lexicographically smallest maximum one):
//!
//! * [`core_decomposition`]: k-cores by the bucket peeling of Batagelj & Zaversnik (2003).
//!   A vertex of core number `c` lies in no clique larger than `c + 1`, so once a clique of
//!   size `s` is known every vertex with core number `< s` is dropped before the search
//!   (the up-front pruning of PMC, Rossi et al. 2015).
//! * [`heuristic_clique`]: the PMC heuristic (Rossi et al. 2015): from each vertex, greedily
//!   grow a clique through neighbours of highest core number.
//! * [`maximum_clique`]: exact branch and bound with greedy-colouring bounds (Tomita & Seki
//!   2003, MCQ), on bitsets as in BBMC (San Segundo et al. 2011), vertices in degeneracy
//!   (minimum-width) order, seeded with the heuristic and an optional warm start.

use std::ops::Range;
use std::time::{Duration, Instant};

const WORD: usize = 64;

fn words_for(n: usize) -> usize {
    n.div_ceil(WORD)
}

fn has_bit(set: &[u64], i: usize) -> bool {
    set.get(i / WORD).is_some_and(|w| w >> (i % WORD) & 1 == 1)
}

fn set_bit(set: &mut [u64], i: usize) {
    if let Some(w) = set.get_mut(i / WORD) {
        *w |= 1 << (i % WORD);
    }
}

fn clear_bit(set: &mut [u64], i: usize) {
    if let Some(w) = set.get_mut(i / WORD) {
        *w &= !(1 << (i % WORD));
    }
}

fn intersect(set: &mut [u64], with: &[u64]) {
    set.iter_mut().zip(with).for_each(|(s, w)| *s &= w);
}

/// Lowest set bit at or after word `from`: the colouring scans left to right, so callers
/// pass the word where the previous scan stopped instead of rescanning cleared words.
fn first_bit_from(set: &[u64], from: usize) -> Option<usize> {
    set.iter()
        .enumerate()
        .skip(from)
        .find(|(_, w)| **w != 0)
        .map(|(i, w)| i * WORD + w.trailing_zeros() as usize)
}

fn ones(set: &[u64]) -> impl Iterator<Item = usize> + '_ {
    set.iter().enumerate().flat_map(|(i, &word)| {
        let mut w = word;
        std::iter::from_fn(move || {
            (w != 0).then(|| {
                let bit = w.trailing_zeros() as usize;
                w &= w - 1;
                i * WORD + bit
            })
        })
    })
}

/// A vertex index that is not in the graph.
#[derive(Clone, Copy, Debug, PartialEq, Eq, thiserror::Error)]
#[error("vertex {vertex} is out of range for a consistency graph of {len} vertices")]
pub struct VertexOutOfRange {
    /// The offending index.
    pub vertex: usize,
    /// Number of vertices in the graph.
    pub len: usize,
}

/// Undirected graph of pairwise-consistent measurements (PCM, Mangelson et al. 2018).
///
/// Adjacency is one bitset (`u64` words) per vertex, so the set intersections of the
/// clique search (BBMC, San Segundo et al. 2011) are word-parallel. There are no self
/// loops: a measurement's consistency with itself is implicit. The graph only grows
/// ([`ConsistencyGraph::add_vertex`]), as in incremental PCM where new closures arrive.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct ConsistencyGraph {
    n: usize,
    rows: Vec<Vec<u64>>,
}

impl ConsistencyGraph {
    /// A graph of `n` vertices and no edges.
    pub fn new(n: usize) -> Self {
        Self {
            n,
            rows: vec![vec![0; words_for(n)]; n],
        }
    }

    /// Number of vertices.
    pub fn len(&self) -> usize {
        self.n
    }

    /// True when the graph has no vertex.
    pub fn is_empty(&self) -> bool {
        self.n == 0
    }

    /// The vertex indices, `0..len()`.
    pub fn vertices(&self) -> Range<usize> {
        0..self.n
    }

    /// Appends an isolated vertex and returns its index. Rows gain a word only every 64
    /// vertices, so growing one closure at a time is amortized O(1) per row.
    pub fn add_vertex(&mut self) -> usize {
        let v = self.n;
        self.n += 1;
        let words = words_for(self.n);
        if words > words_for(v) {
            for row in &mut self.rows {
                row.resize(words, 0);
            }
        }
        self.rows.push(vec![0; words]);
        v
    }

    /// Joins `a` and `b`; returns whether the edge is new. A self loop is ignored
    /// (returns `false`) because the diagonal is implicit.
    pub fn add_edge(&mut self, a: usize, b: usize) -> Result<bool, VertexOutOfRange> {
        for vertex in [a, b] {
            if vertex >= self.n {
                return Err(VertexOutOfRange {
                    vertex,
                    len: self.n,
                });
            }
        }
        if a == b || self.has_edge(a, b) {
            return Ok(false);
        }
        set_bit(&mut self.rows[a], b);
        set_bit(&mut self.rows[b], a);
        Ok(true)
    }

    /// Whether `a` and `b` are joined; `false` for out-of-range indices and for `a == b`.
    pub fn has_edge(&self, a: usize, b: usize) -> bool {
        b < self.n && self.rows.get(a).is_some_and(|row| has_bit(row, b))
    }

    /// Number of neighbours of `v` (0 when out of range).
    pub fn degree(&self, v: usize) -> usize {
        self.rows
            .get(v)
            .map_or(0, |row| row.iter().map(|w| w.count_ones() as usize).sum())
    }

    /// Neighbours of `v` in increasing order (none when out of range).
    pub fn neighbors(&self, v: usize) -> impl Iterator<Item = usize> + '_ {
        ones(self.rows.get(v).map_or(&[][..], Vec::as_slice))
    }

    /// Number of edges.
    pub fn edge_count(&self) -> usize {
        self.vertices().map(|v| self.degree(v)).sum::<usize>() / 2
    }

    /// Whether `vertices` are distinct, in range and pairwise joined.
    pub fn is_clique(&self, vertices: &[usize]) -> bool {
        vertices.iter().all(|&v| v < self.n)
            && vertices
                .iter()
                .enumerate()
                .all(|(i, &a)| vertices[i + 1..].iter().all(|&b| self.has_edge(a, b)))
    }
}

/// k-core decomposition (Batagelj & Zaversnik 2003, bucket peeling, O(n²/64 + m)).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct CoreDecomposition {
    /// `core_numbers[v]`: largest `k` such that `v` belongs to the k-core. A clique
    /// containing `v` has at most `core_numbers[v] + 1` vertices.
    pub core_numbers: Vec<usize>,
    /// Vertices in the order the peeling removes them (core numbers non-decreasing).
    /// Reversed, it is the degeneracy (minimum-width) order used by MCS and BBMC.
    pub peel_order: Vec<usize>,
}

impl CoreDecomposition {
    /// The degeneracy of the graph: the largest core number (0 for an empty graph).
    pub fn degeneracy(&self) -> usize {
        self.core_numbers.iter().copied().max().unwrap_or(0)
    }
}

/// Core numbers and peeling order of `graph` by the Batagelj & Zaversnik (2003) algorithm:
/// repeatedly remove a vertex of minimum remaining degree. Among vertices of equal degree
/// the higher index is removed first, so the result is deterministic.
pub fn core_decomposition(graph: &ConsistencyGraph) -> CoreDecomposition {
    let n = graph.len();
    let mut deg: Vec<usize> = graph.vertices().map(|v| graph.degree(v)).collect();
    let max_deg = deg.iter().copied().max().unwrap_or(0);
    // bin[d]: first position in `vert` of the vertices of current degree d.
    let mut bin = vec![0usize; max_deg + 1];
    for &d in &deg {
        bin[d] += 1;
    }
    let mut start = 0;
    for b in &mut bin {
        (*b, start) = (start, start + *b);
    }
    let mut pos = vec![0usize; n];
    let mut vert = vec![0usize; n];
    let mut next = bin.clone();
    // Reverse index order within a bucket: the degeneracy order is the peel order reversed,
    // so equal vertices then come out low index first.
    for v in (0..n).rev() {
        pos[v] = next[deg[v]];
        vert[pos[v]] = v;
        next[deg[v]] += 1;
    }
    for i in 0..n {
        let v = vert[i];
        for u in graph.neighbors(v) {
            if deg[u] > deg[v] {
                // Move u to the front of its bucket, then shrink the bucket past it.
                let (du, pu) = (deg[u], pos[u]);
                let pw = bin[du];
                let w = vert[pw];
                if u != w {
                    pos[u] = pw;
                    vert[pu] = w;
                    pos[w] = pu;
                    vert[pw] = u;
                }
                bin[du] += 1;
                deg[u] -= 1;
            }
        }
    }
    CoreDecomposition {
        core_numbers: deg,
        peel_order: vert,
    }
}

/// The graph relabelled in degeneracy order (new vertex 0 = last peeled, highest core) as
/// one flat bitset matrix. In this order "lowest index" means "highest core number", and
/// the vertices of core number ≥ k form a prefix, so PMC pruning is a prefix mask.
struct Ordered {
    words: usize,
    adj: Vec<u64>,
    /// `old[new]` and `new[old]`: the relabelling both ways.
    old: Vec<usize>,
    new: Vec<usize>,
    core: Vec<usize>,
}

impl Ordered {
    fn new(graph: &ConsistencyGraph, cores: &CoreDecomposition) -> Self {
        let old: Vec<usize> = cores.peel_order.iter().rev().copied().collect();
        let mut new = vec![0usize; graph.len()];
        for (i, &o) in old.iter().enumerate() {
            new[o] = i;
        }
        let words = words_for(old.len());
        let mut adj = vec![0u64; old.len() * words];
        // `max(1)`: chunks cannot be empty; with no vertex there is no row anyway.
        for (row, &o) in adj.chunks_exact_mut(words.max(1)).zip(&old) {
            for u in graph.neighbors(o) {
                set_bit(row, new[u]);
            }
        }
        let core = old.iter().map(|&o| cores.core_numbers[o]).collect();
        Self {
            words,
            adj,
            old,
            new,
            core,
        }
    }

    fn row(&self, v: usize) -> &[u64] {
        &self.adj[v * self.words..(v + 1) * self.words]
    }

    /// Bitset of the vertices that may still belong to a clique larger than `size`.
    fn candidates_beyond(&self, size: usize) -> Vec<u64> {
        let k = self.core.partition_point(|&c| c >= size);
        let mut set = vec![0u64; self.words];
        set[..k / WORD].fill(u64::MAX);
        if k % WORD != 0 {
            set[k / WORD] = (1 << (k % WORD)) - 1;
        }
        set
    }

    /// Extends `clique` (new labels) greedily, adding the lowest-labelled (highest-core)
    /// common neighbour until none is left.
    fn extend(&self, clique: &mut Vec<usize>, mut common: Vec<u64>) {
        while let Some(u) = first_bit_from(&common, 0) {
            clique.push(u);
            intersect(&mut common, self.row(u));
        }
    }

    /// PMC heuristic (Rossi et al. 2015): for every vertex whose core number still allows
    /// a larger clique, grow a clique greedily among its neighbours of sufficient core.
    /// Stops early, keeping the best so far, once `deadline` has passed.
    fn pmc_heuristic(&self, deadline: Option<Instant>) -> Vec<usize> {
        let mut best: Vec<usize> = Vec::new();
        for v in 0..self.old.len() {
            // Core numbers are non-increasing in this order: no later vertex can do better.
            if self.core[v] < best.len() {
                break;
            }
            if v % 64 == 63 && deadline.is_some_and(|d| Instant::now() >= d) {
                break;
            }
            let mut common = self.candidates_beyond(best.len());
            intersect(&mut common, self.row(v));
            let mut clique = vec![v];
            self.extend(&mut clique, common);
            if clique.len() > best.len() {
                best = clique;
            }
        }
        best
    }

    /// The warm start in new labels: `initial` in its order, keeping each in-range vertex
    /// joined to all kept ones, then extended to a maximal clique.
    fn repair(&self, initial: &[usize]) -> Vec<usize> {
        let mut warm = Vec::new();
        let mut common = vec![u64::MAX; self.words];
        for &v in initial.iter().filter_map(|&o| self.new.get(o)) {
            if has_bit(&common, v) {
                warm.push(v);
                intersect(&mut common, self.row(v));
            }
        }
        // Bits past the last vertex are set in `common` only while `warm` is empty.
        if !warm.is_empty() {
            self.extend(&mut warm, common);
        }
        warm
    }

    fn to_old(&self, clique: &[usize]) -> Vec<usize> {
        let mut out: Vec<usize> = clique.iter().map(|&v| self.old[v]).collect();
        out.sort_unstable();
        out
    }
}

/// Largest clique found by the PMC heuristic (Rossi et al. 2015, greedy in k-core order),
/// sorted. Always a clique; maximal but not necessarily maximum. O(n · ω · n/64).
pub fn heuristic_clique(graph: &ConsistencyGraph) -> Vec<usize> {
    let ordered = Ordered::new(graph, &core_decomposition(graph));
    ordered.to_old(&ordered.pmc_heuristic(None))
}

/// Options of [`maximum_clique`].
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct CliqueOptions {
    /// A known clique to start from, e.g. the previous maximum clique in incremental PCM
    /// plus new closures. Taken in the given order, keeping each vertex that is in range
    /// and joined to all kept ones (so a stale warm start is repaired, not rejected), then
    /// extended greedily. On a tie in size it is preferred over the heuristic's clique,
    /// which keeps the inlier set stable across increments.
    pub initial: Option<Vec<usize>>,
    /// Wall-clock budget for the whole call. When it runs out the best clique so far is
    /// returned with `exact: false`; only then does the output depend on timing.
    pub time_budget: Option<Duration>,
}

/// Outcome of [`maximum_clique`].
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct CliqueResult {
    /// The clique, sorted by vertex index.
    pub vertices: Vec<usize>,
    /// True when the search completed, proving no larger clique exists.
    pub exact: bool,
    /// Branch-and-bound nodes (colourings) performed.
    pub nodes_explored: u64,
}

/// Exact maximum clique by branch and bound with greedy-colouring bounds (Tomita & Seki
/// 2003, MCQ) on bitsets (BBMC, San Segundo et al. 2011), vertices in degeneracy order.
///
/// The lower bound starts from the PMC heuristic (Rossi et al. 2015) and the warm start of
/// `options.initial`; vertices whose core number cannot beat it are pruned before the
/// search. Deterministic unless `options.time_budget` expires.
pub fn maximum_clique(graph: &ConsistencyGraph, options: &CliqueOptions) -> CliqueResult {
    let deadline = options
        .time_budget
        .and_then(|budget| Instant::now().checked_add(budget));
    let ordered = Ordered::new(graph, &core_decomposition(graph));

    let mut best = ordered.pmc_heuristic(deadline);
    if let Some(initial) = &options.initial {
        let warm = ordered.repair(initial);
        if warm.len() >= best.len() {
            best = warm;
        }
    }

    let mut search = Search {
        g: &ordered,
        best,
        nodes: 0,
        deadline,
        levels: Vec::new(),
        uncolored: Vec::with_capacity(ordered.words),
        class: Vec::with_capacity(ordered.words),
    };
    let exact = search.run();
    CliqueResult {
        vertices: ordered.to_old(&search.best),
        exact,
        nodes_explored: search.nodes,
    }
}

/// One depth of the branch and bound: candidate set, and the candidates to branch on in
/// colour order with their colours (the bound), consumed from the back.
#[derive(Default)]
struct Level {
    candidates: Vec<u64>,
    order: Vec<usize>,
    colors: Vec<usize>,
}

/// BBMC state. The recursion is an explicit stack of [`Level`]s so that deep cliques (PCM
/// graphs routinely have cliques of hundreds) cannot overflow a thread's stack, and the
/// per-depth buffers are reused.
struct Search<'a> {
    g: &'a Ordered,
    best: Vec<usize>,
    nodes: u64,
    deadline: Option<Instant>,
    levels: Vec<Level>,
    /// Colouring buffers: vertices not yet coloured, and the current colour class.
    uncolored: Vec<u64>,
    class: Vec<u64>,
}

impl Search<'_> {
    /// Runs the search; returns whether it completed before the deadline.
    fn run(&mut self) -> bool {
        let root = self.g.candidates_beyond(self.best.len());
        if root.iter().all(|&w| w == 0) {
            return true; // core numbers alone prove `best` maximum
        }
        let mut clique: Vec<usize> = Vec::new();
        if !self.open(0, root, 0) {
            return false;
        }
        let mut depth = 0;
        loop {
            let level = &mut self.levels[depth];
            let next = match (level.order.pop(), level.colors.pop()) {
                (Some(v), Some(color)) if clique.len() + color > self.best.len() => Some(v),
                _ => None,
            };
            let Some(v) = next else {
                // Bound reached or level exhausted: back up.
                if depth == 0 {
                    return true;
                }
                depth -= 1;
                clique.pop();
                continue;
            };
            let mut child = std::mem::take(&mut self.levels[depth + 1].candidates);
            let parent = &mut self.levels[depth].candidates;
            child.clear();
            child.extend(parent.iter().zip(self.g.row(v)).map(|(c, a)| c & a));
            clear_bit(parent, v);
            clique.push(v);
            if child.iter().all(|&w| w == 0) {
                if clique.len() > self.best.len() {
                    self.best.clone_from(&clique);
                }
                clique.pop();
                self.levels[depth + 1].candidates = child;
                continue;
            }
            if !self.open(depth + 1, child, clique.len()) {
                return false;
            }
            depth += 1;
        }
    }

    /// Creates the search node at `depth` over `candidates`: greedy sequential colouring
    /// (Tomita & Seki 2003) done one colour class at a time on bitsets (San Segundo 2011).
    /// Only vertices whose colour could beat the incumbent are recorded as branches
    /// (`kmin`, as in MCS/BBMC); the rest stay candidates of deeper levels. Returns `false`
    /// when the time budget has run out (checked every 64 nodes, and at the root).
    fn open(&mut self, depth: usize, candidates: Vec<u64>, clique_len: usize) -> bool {
        if self.nodes.is_multiple_of(64) && self.deadline.is_some_and(|d| Instant::now() >= d) {
            return false;
        }
        self.nodes += 1;
        // The child level must exist too: its candidate buffer is taken when branching.
        if self.levels.len() < depth + 2 {
            self.levels.resize_with(depth + 2, Level::default);
        }
        let kmin = (self.best.len() + 1).saturating_sub(clique_len).max(1);
        let g = self.g;
        let level = &mut self.levels[depth];
        level.order.clear();
        level.colors.clear();
        let uncolored = &mut self.uncolored;
        uncolored.clear();
        uncolored.extend_from_slice(&candidates);
        let class = &mut self.class;
        class.clear();
        class.resize(uncolored.len(), 0);
        let mut color = 0;
        let mut first_word = 0;
        while let Some(start) = first_bit_from(uncolored, first_word) {
            first_word = start / WORD;
            color += 1;
            class.copy_from_slice(uncolored);
            let mut from = first_word;
            while let Some(v) = first_bit_from(class, from) {
                from = v / WORD;
                clear_bit(uncolored, v);
                clear_bit(class, v);
                // Bits before v are already clear, so only words from v's on matter.
                for (c, a) in class[from..].iter_mut().zip(&g.row(v)[from..]) {
                    *c &= !a;
                }
                if color >= kmin {
                    level.order.push(v);
                    level.colors.push(color);
                }
            }
        }
        level.candidates = candidates;
        true
    }
}
