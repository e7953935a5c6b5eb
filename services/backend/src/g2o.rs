//! g2o files: `VERTEX_SE2`, `EDGE_SE2`, `VERTEX_SE3:QUAT`, `EDGE_SE3:QUAT` (and `FIX`).
//!
//! g2o stores information matrices in translation-first order; the solver uses
//! rotation-first (see [`doorslam_geometry::lie`]): the blocks are permuted here and only here.
//! Files without `VERTEX` lines (or with edges to poses that have none) get initial
//! poses by chaining edges outward from the first pose (a spanning tree, file order).
//!
//! Information matrices pass the same check as [`PoseGraph::add_edge`]
//! ([`check_information`]). Some public benchmark files have indefinite ones (SE-Sync's
//! cubicle: 5,021 of 16,869 edges); [`InformationPolicy`] decides what happens to them.

use std::io::Write;
use std::path::Path;

use nalgebra::{Isometry2, Isometry3, Translation3, UnitQuaternion};

use crate::graph::PoseGraph;
use doorslam_geometry::information::{
    check_information, nearest_positive_definite, InformationCheck, InformationError,
};
use doorslam_geometry::{LieGroup, TangentMatrix, SO3};

/// How many line numbers [`GraphError::NotPositiveDefinite`] lists.
const LINES_SHOWN: usize = 10;

/// Errors of reading or writing a graph file; parse errors name the file and line.
#[derive(Debug, thiserror::Error)]
pub enum GraphError {
    #[error("{file}: {source}")]
    Io {
        file: String,
        #[source]
        source: std::io::Error,
    },
    #[error("{file}:{line}: {msg}")]
    Parse {
        file: String,
        line: usize,
        msg: String,
    },
    #[error("{file}: {msg}")]
    Graph { file: String, msg: String },
    /// Edges whose information matrix is not positive definite, with the default
    /// [`InformationPolicy::Check`]. The whole file is read first, so this counts them all.
    #[error("{}", not_positive_definite_message(.file, .lines, *.count, *.edges))]
    NotPositiveDefinite {
        file: String,
        /// Line numbers of the first ones (at most 10).
        lines: Vec<usize>,
        /// How many edges have one.
        count: usize,
        /// Edges in the file.
        edges: usize,
    },
}

fn not_positive_definite_message(
    file: &str,
    lines: &[usize],
    count: usize,
    edges: usize,
) -> String {
    let listed = lines
        .iter()
        .map(usize::to_string)
        .collect::<Vec<_>>()
        .join(", ");
    let more = match count.saturating_sub(lines.len()) {
        0 => String::new(),
        n => format!(" and {n} more"),
    };
    format!(
        "{file}:{}: information matrix is not positive definite; {count} of {edges} edges have \
         one (lines {listed}{more}). Use them as written with --information as-is, or replace \
         each by the nearest positive-definite matrix with --information nearest-pd",
        lines.first().copied().unwrap_or(0)
    )
}

/// What the reader does with an information matrix that is not positive definite (one
/// that is not finite or not symmetric is always an error).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum InformationPolicy {
    /// Refuse the file ([`GraphError::NotPositiveDefinite`]): the cost is not a sum of
    /// squares with such a matrix, so the problem is not what the file claims to be.
    #[default]
    Check,
    /// Keep the matrix as written ([`InformationCheck::AsIs`]). The objective is then not
    /// a sum of squares and may be unbounded below; the solver says so
    /// ([`crate::solver::StopReason::NegativeCost`]) rather than call it converged.
    AsIs,
    /// Replace it by the nearest positive-definite matrix
    /// ([`crate::graph::nearest_positive_definite`]).
    NearestPd,
}

/// Options of [`read_g2o_with`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct ReadOptions {
    pub unknown: UnknownTags,
    pub information: InformationPolicy,
}

/// A graph read from a file: planar or 3-D.
#[derive(Debug, Clone)]
pub enum Graph {
    Se2(PoseGraph<Isometry2<f64>>),
    Se3(PoseGraph<Isometry3<f64>>),
}

/// How to treat lines with tags this reader does not know.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum UnknownTags {
    /// An unknown tag is an error (default: a typo or an unsupported factor must not
    /// silently change the problem).
    #[default]
    Error,
    /// Skip the line and record a warning.
    Skip,
}

/// The result of reading: the graph, the keys g2o marked `FIX`, and warnings.
#[derive(Debug, Clone)]
pub struct G2oFile {
    pub graph: Graph,
    pub fixed: Vec<u64>,
    pub warnings: Vec<String>,
    /// Poses that had no VERTEX line and were initialized by chaining edges.
    pub chained: usize,
    /// Per pose index: whether the file had a VERTEX line for it.
    pub has_vertex: Vec<bool>,
    /// Line numbers of the edges whose information matrix is not positive definite (kept
    /// as written or repaired, per [`InformationPolicy`]; empty with `Check`).
    pub not_positive_definite: Vec<usize>,
    /// Edges whose information matrix was replaced ([`InformationPolicy::NearestPd`]).
    pub repaired_edges: usize,
}

struct Ctx<'a> {
    file: &'a str,
    line: usize,
}

impl Ctx<'_> {
    fn err(&self, msg: impl Into<String>) -> GraphError {
        GraphError::Parse {
            file: self.file.to_string(),
            line: self.line,
            msg: msg.into(),
        }
    }
    fn numbers<const N: usize>(&self, tag: &str, fields: &[&str]) -> Result<[f64; N], GraphError> {
        if fields.len() != N {
            return Err(self.err(format!(
                "{tag} needs {N} numbers after the tag, found {}",
                fields.len()
            )));
        }
        let mut out = [0.0; N];
        for (k, f) in fields.iter().enumerate() {
            let v: f64 = f
                .parse()
                .map_err(|_| self.err(format!("{tag}: field {} {f:?} is not a number", k + 1)))?;
            if !v.is_finite() {
                return Err(self.err(format!("{tag}: field {} is {f}, not finite", k + 1)));
            }
            out[k] = v;
        }
        Ok(out)
    }
    fn key(&self, tag: &str, f: &str) -> Result<u64, GraphError> {
        f.parse()
            .map_err(|_| self.err(format!("{tag}: {f:?} is not a pose id (unsigned integer)")))
    }
    fn quaternion(
        &self,
        tag: &str,
        x: f64,
        y: f64,
        z: f64,
        w: f64,
    ) -> Result<UnitQuaternion<f64>, GraphError> {
        // The same rule as every other input of a pose (doorslam_geometry::SO3).
        SO3::from_quaternion_checked(x, y, z, w)
            .map(|r| r.quaternion())
            .map_err(|e| self.err(format!("{tag}: quaternion ({x}, {y}, {z}, {w}): {e}")))
    }
    /// Symmetric matrix from the row-major upper triangle, permuted by `order`
    /// (file index -> solver index), checked by [`check_information`]; returns it with
    /// whether it is positive definite (what to do if not is the caller's policy).
    fn information(
        &self,
        tag: &str,
        upper: &[f64],
        n: usize,
        order: &[usize],
    ) -> Result<(TangentMatrix, bool), GraphError> {
        let mut m = TangentMatrix::zeros();
        let mut k = 0;
        for r in 0..n {
            for c in r..n {
                let (a, b) = (order[r], order[c]);
                m[(a, b)] = upper[k];
                m[(b, a)] = upper[k];
                k += 1;
            }
        }
        match check_information(&m, n, InformationCheck::PositiveDefinite) {
            Ok(()) => Ok((m, true)),
            Err(InformationError::NotPositiveDefinite) => Ok((m, false)),
            Err(e) => Err(self.err(format!("{tag}: {e}"))),
        }
    }
}

/// Translation-first (g2o) to rotation-first (solver) index maps.
const SE3_ORDER: [usize; 6] = [3, 4, 5, 0, 1, 2];
const SE2_ORDER: [usize; 3] = [1, 2, 0];

enum Dimension {
    Unknown,
    Two,
    Three,
}

/// An edge as read: keys, measurement, information, line, and how to check it.
type RawEdge<G> = (u64, u64, G, TangentMatrix, usize, InformationCheck);

/// Reads a g2o file, refusing information matrices that are not positive definite.
pub fn read_g2o(path: &Path, unknown: UnknownTags) -> Result<G2oFile, GraphError> {
    read_g2o_with(
        path,
        ReadOptions {
            unknown,
            ..Default::default()
        },
    )
}

/// Reads a g2o file with explicit options.
pub fn read_g2o_with(path: &Path, options: ReadOptions) -> Result<G2oFile, GraphError> {
    let file = path.display().to_string();
    let text = std::fs::read_to_string(path).map_err(|source| GraphError::Io {
        file: file.clone(),
        source,
    })?;
    parse_g2o_with(&text, &file, options)
}

/// Parses g2o text; `file` names the source in errors.
pub fn parse_g2o(text: &str, file: &str, unknown: UnknownTags) -> Result<G2oFile, GraphError> {
    parse_g2o_with(
        text,
        file,
        ReadOptions {
            unknown,
            ..Default::default()
        },
    )
}

/// Applies the policy to one edge's information matrix: the matrix to use, how the graph
/// must check it, and whether it was not positive definite.
fn apply_policy(
    ctx: &Ctx<'_>,
    tag: &str,
    (m, pd): (TangentMatrix, bool),
    n: usize,
    policy: InformationPolicy,
) -> Result<(TangentMatrix, InformationCheck, bool), GraphError> {
    if pd {
        return Ok((m, InformationCheck::PositiveDefinite, false));
    }
    match policy {
        // Kept for now: the error at the end counts every bad edge of the file.
        InformationPolicy::Check => Ok((m, InformationCheck::PositiveDefinite, true)),
        InformationPolicy::AsIs => Ok((m, InformationCheck::AsIs, true)),
        InformationPolicy::NearestPd => {
            let repaired = nearest_positive_definite(&m, n)
                .filter(|r| check_information(r, n, InformationCheck::PositiveDefinite).is_ok())
                .ok_or_else(|| {
                    ctx.err(format!(
                        "{tag}: information matrix has no positive-definite repair (all entries zero?)"
                    ))
                })?;
            Ok((repaired, InformationCheck::PositiveDefinite, true))
        }
    }
}

/// Parses g2o text with explicit options; `file` names the source in errors.
pub fn parse_g2o_with(text: &str, file: &str, options: ReadOptions) -> Result<G2oFile, GraphError> {
    let unknown = options.unknown;
    let mut g2 = PoseGraph::<Isometry2<f64>>::new();
    let mut g3 = PoseGraph::<Isometry3<f64>>::new();
    // Vertices may come after the edges that use them: collect, then build.
    let mut v2: Vec<(u64, Isometry2<f64>)> = Vec::new();
    let mut v3: Vec<(u64, Isometry3<f64>)> = Vec::new();
    let mut e2: Vec<RawEdge<Isometry2<f64>>> = Vec::new();
    let mut e3: Vec<RawEdge<Isometry3<f64>>> = Vec::new();
    let mut not_pd = Vec::new();
    let mut dim = Dimension::Unknown;
    let mut fixed = Vec::new();
    let mut warnings = Vec::new();
    for (n, raw) in text.lines().enumerate() {
        let ctx = Ctx { file, line: n + 1 };
        let line = raw.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let mut it = line.split_whitespace();
        let tag = it.next().unwrap_or_default();
        let fields: Vec<&str> = it.collect();
        let mut set_dim = |d: Dimension| -> Result<(), GraphError> {
            match (&dim, &d) {
                (Dimension::Unknown, _) => {
                    dim = d;
                    Ok(())
                }
                (Dimension::Two, Dimension::Two) | (Dimension::Three, Dimension::Three) => Ok(()),
                _ => Err(ctx.err(format!("{tag} mixes 2-D and 3-D elements in one graph"))),
            }
        };
        match tag {
            "VERTEX_SE2" => {
                set_dim(Dimension::Two)?;
                let (id, rest) = fields.split_first().ok_or_else(|| ctx.err("VERTEX_SE2 without an id"))?;
                let [x, y, th] = ctx.numbers::<3>(tag, rest)?;
                v2.push((ctx.key(tag, id)?, Isometry2::new(nalgebra::Vector2::new(x, y), th)));
            }
            "EDGE_SE2" => {
                set_dim(Dimension::Two)?;
                if fields.len() < 2 {
                    return Err(ctx.err("EDGE_SE2 needs two pose ids"));
                }
                let (i, j) = (ctx.key(tag, fields[0])?, ctx.key(tag, fields[1])?);
                let v = ctx.numbers::<9>(tag, &fields[2..])?;
                let info = ctx.information(tag, &v[3..], 3, &SE2_ORDER)?;
                let (info, check, bad) = apply_policy(&ctx, tag, info, 3, options.information)?;
                if bad {
                    not_pd.push(ctx.line);
                }
                let z = Isometry2::new(nalgebra::Vector2::new(v[0], v[1]), v[2]);
                e2.push((i, j, z, info, ctx.line, check));
            }
            "VERTEX_SE3:QUAT" => {
                set_dim(Dimension::Three)?;
                let (id, rest) = fields.split_first().ok_or_else(|| ctx.err("VERTEX_SE3:QUAT without an id"))?;
                let [x, y, z, qx, qy, qz, qw] = ctx.numbers::<7>(tag, rest)?;
                let q = ctx.quaternion(tag, qx, qy, qz, qw)?;
                v3.push((ctx.key(tag, id)?, Isometry3::from_parts(Translation3::new(x, y, z), q)));
            }
            "EDGE_SE3:QUAT" => {
                set_dim(Dimension::Three)?;
                if fields.len() < 2 {
                    return Err(ctx.err("EDGE_SE3:QUAT needs two pose ids"));
                }
                let (i, j) = (ctx.key(tag, fields[0])?, ctx.key(tag, fields[1])?);
                let v = ctx.numbers::<28>(tag, &fields[2..])?;
                let q = ctx.quaternion(tag, v[3], v[4], v[5], v[6])?;
                let info = ctx.information(tag, &v[7..], 6, &SE3_ORDER)?;
                let (info, check, bad) = apply_policy(&ctx, tag, info, 6, options.information)?;
                if bad {
                    not_pd.push(ctx.line);
                }
                let z = Isometry3::from_parts(Translation3::new(v[0], v[1], v[2]), q);
                e3.push((i, j, z, info, ctx.line, check));
            }
            "FIX" => {
                for f in &fields {
                    fixed.push(ctx.key(tag, f)?);
                }
            }
            _ => match unknown {
                UnknownTags::Error => {
                    return Err(ctx.err(format!(
                        "unknown tag {tag:?} (supported: VERTEX_SE2, EDGE_SE2, VERTEX_SE3:QUAT, EDGE_SE3:QUAT, FIX); skip such lines with --skip-unknown"
                    )))
                }
                UnknownTags::Skip => warnings.push(format!("{file}:{}: skipped unknown tag {tag:?}", n + 1)),
            },
        }
    }
    if options.information == InformationPolicy::Check && !not_pd.is_empty() {
        return Err(GraphError::NotPositiveDefinite {
            file: file.into(),
            lines: not_pd.iter().copied().take(LINES_SHOWN).collect(),
            count: not_pd.len(),
            edges: e2.len() + e3.len(),
        });
    }
    let repaired_edges = match options.information {
        InformationPolicy::NearestPd => not_pd.len(),
        _ => 0,
    };
    let (graph, has_vertex) = match dim {
        Dimension::Unknown => {
            return Err(GraphError::Graph {
                file: file.into(),
                msg: "no vertices or edges".into(),
            })
        }
        Dimension::Two => {
            let known = assemble(&mut g2, v2, e2, file)?;
            (Graph::Se2(g2), known)
        }
        Dimension::Three => {
            let known = assemble(&mut g3, v3, e3, file)?;
            (Graph::Se3(g3), known)
        }
    };
    let chained = has_vertex.iter().filter(|k| !**k).count();
    Ok(G2oFile {
        graph,
        fixed,
        warnings,
        chained,
        has_vertex,
        not_positive_definite: not_pd,
        repaired_edges,
    })
}

/// Builds the graph: vertices in file order, then poses only edges mention, initialized
/// by chaining edges breadth-first from the first pose. Returns, per pose, whether it had
/// a VERTEX line.
fn assemble<G: LieGroup>(
    g: &mut PoseGraph<G>,
    vertices: Vec<(u64, G)>,
    edges: Vec<RawEdge<G>>,
    file: &str,
) -> Result<Vec<bool>, GraphError> {
    let mut known = vec![];
    for (k, p) in vertices {
        let before = g.len();
        let idx = g.add_pose(k, p);
        if idx == before {
            known.push(true);
        }
    }
    for (i, j, ..) in &edges {
        for k in [*i, *j] {
            if g.index_of(k).is_none() {
                g.add_pose(k, G::identity());
                known.push(false);
            }
        }
    }
    for (i, j, z, info, line, check) in edges {
        // Every key got a pose just above.
        let (a, b) = (g.index_of(i).unwrap_or(0), g.index_of(j).unwrap_or(0));
        g.add_edge_with(a, b, z, info, check)
            .map_err(|e| GraphError::Parse {
                file: file.into(),
                line,
                msg: e.to_string(),
            })?;
    }
    if known.iter().all(|k| *k) {
        return Ok(known);
    }
    let start = known.iter().position(|k| *k).unwrap_or(0);
    crate::init::chain(g, start, &known);
    let reached = g.reachable_from(start);
    if let Some(p) = (0..g.len()).find(|&p| !reached[p]) {
        return Err(GraphError::Graph {
            file: file.into(),
            msg: format!(
                "pose {} has no VERTEX line and no chain of edges to the first pose",
                doorslam_geometry::key::label(g.keys()[p])
            ),
        });
    }
    Ok(known)
}

fn upper_triangle(m: &TangentMatrix, n: usize, order: &[usize]) -> Vec<f64> {
    let mut out = Vec::with_capacity(n * (n + 1) / 2);
    for r in 0..n {
        for c in r..n {
            out.push(m[(order[r], order[c])]);
        }
    }
    out
}

fn join(v: &[f64]) -> String {
    v.iter()
        .map(|x| format!("{x:.17e}"))
        .collect::<Vec<_>>()
        .join(" ")
}

/// Writes a graph as g2o (full precision), in the same element types it was read with.
pub fn write_g2o(graph: &Graph, path: &Path) -> Result<(), GraphError> {
    let file = path.display().to_string();
    let io = |source| GraphError::Io {
        file: file.clone(),
        source,
    };
    let mut w = std::io::BufWriter::new(std::fs::File::create(path).map_err(io)?);
    match graph {
        Graph::Se2(g) => {
            for (k, p) in g.keys().iter().zip(g.poses()) {
                let t = p.translation.vector;
                writeln!(
                    w,
                    "VERTEX_SE2 {k} {}",
                    join(&[t.x, t.y, p.rotation.angle()])
                )
                .map_err(io)?;
            }
            for e in g.edges() {
                let t = e.measured.translation.vector;
                let info = upper_triangle(&e.information, 3, &SE2_ORDER);
                let (a, b) = (g.keys()[e.i], g.keys()[e.j]);
                writeln!(
                    w,
                    "EDGE_SE2 {a} {b} {} {}",
                    join(&[t.x, t.y, e.measured.rotation.angle()]),
                    join(&info)
                )
                .map_err(io)?;
            }
        }
        Graph::Se3(g) => {
            for (k, p) in g.keys().iter().zip(g.poses()) {
                writeln!(w, "{}", se3_vertex_line(*k, p)).map_err(io)?;
            }
            for e in g.edges() {
                let (a, b) = (g.keys()[e.i], g.keys()[e.j]);
                writeln!(w, "{}", se3_edge_line(a, b, &e.measured, &e.information)).map_err(io)?;
            }
        }
    }
    w.flush().map_err(io)
}

/// A `VERTEX_SE3:QUAT` line (no newline).
pub fn se3_vertex_line(k: u64, p: &Isometry3<f64>) -> String {
    format!("VERTEX_SE3:QUAT {k} {}", join(&pose7(p)))
}

/// An `EDGE_SE3:QUAT` line (no newline): `z ≈ X_a⁻¹ X_b`, information given rotation-first
/// (the solver's order) and written in g2o's translation-first order.
pub fn se3_edge_line(a: u64, b: u64, z: &Isometry3<f64>, information: &TangentMatrix) -> String {
    let info = upper_triangle(information, 6, &SE3_ORDER);
    format!("EDGE_SE3:QUAT {a} {b} {} {}", join(&pose7(z)), join(&info))
}

/// Several 3-D g2o files (one per robot, with multi-robot keys) as one team graph: a pose
/// takes the first file's `VERTEX` line that has one (else it is chained from edges), and
/// an edge found in several files with the same keys and the same measurement bits (an
/// inter-robot closure both robots wrote) is kept once.
pub fn merge_g2o_files(
    files: &[std::path::PathBuf],
    options: ReadOptions,
) -> Result<(PoseGraph<Isometry3<f64>>, Vec<String>), GraphError> {
    let mut merged = PoseGraph::new();
    let mut warnings = Vec::new();
    let mut seen_edges = std::collections::BTreeSet::new();
    let check = match options.information {
        InformationPolicy::AsIs => InformationCheck::AsIs,
        _ => InformationCheck::PositiveDefinite,
    };
    for path in files {
        let file = read_g2o_with(path, options)?;
        warnings.extend(file.warnings);
        let Graph::Se3(g) = file.graph else {
            return Err(GraphError::Parse {
                file: path.display().to_string(),
                line: 0,
                msg: "a team graph needs 3-D poses (VERTEX_SE3:QUAT / EDGE_SE3:QUAT)".into(),
            });
        };
        for (idx, (&k, p)) in g.keys().iter().zip(g.poses()).enumerate() {
            if file.has_vertex[idx] || merged.index_of(k).is_none() {
                merged.add_pose(k, *p);
            }
        }
        for e in g.edges() {
            let (a, b) = (g.keys()[e.i], g.keys()[e.j]);
            let q = e.measured.rotation.coords;
            let t = e.measured.translation.vector;
            let id = (a, b, [t.x, t.y, t.z, q.x, q.y, q.z, q.w].map(f64::to_bits));
            if seen_edges.insert(id) {
                let (i, j) = (
                    merged.index_of(a).unwrap_or_default(),
                    merged.index_of(b).unwrap_or_default(),
                );
                // The reader checked every matrix under the chosen policy.
                merged
                    .add_edge_with(i, j, e.measured, e.information, check)
                    .map_err(|err| GraphError::Parse {
                        file: path.display().to_string(),
                        line: 0,
                        msg: format!("merging edge {a} -> {b}: {err}"),
                    })?;
            }
        }
    }
    Ok((merged, warnings))
}

fn pose7(p: &Isometry3<f64>) -> [f64; 7] {
    let (t, q) = (p.translation.vector, p.rotation.quaternion());
    [t.x, t.y, t.z, q.i, q.j, q.k, q.w]
}
